"""The console commands of the runtime side (dadiff-run, dadiff-eval, dadiff-bench): argument parsing
and the composition roots, the only modules that may join the tracker, evaluation, data making and drone/.
Every command starts in launch.py, which handles signals before the heavy imports."""
