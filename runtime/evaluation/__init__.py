"""Evaluation on the ground: benchmarks, metrics, scene generation, baselines, the demo.

Kept apart from the onboard tracker (the rest of dadiff.runtime) so that runtime/ reads as what flies.
"""
