"""Evaluation on the ground: running trackers over datasets and scoring them (OPE metrics, tables, plots),
where a tracker loses its frames (anatomy, box-read, uncut clips) and tuning its hyper-parameters.

It reads data from dadiff.runtime.datamaking and never the other way round; only the commands import it
(and dadiff-export's int8 check, which scores before it writes). pyproject's import contracts hold this.
"""
