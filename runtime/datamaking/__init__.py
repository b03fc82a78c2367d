"""Data making on the ground: dataset readers, the night-scene generator and its night renderers, the
real-photo library (Debian packages, Qt .rcc), cut-outs, detectors and pseudo-labelled sequences from real video.

Training (dadiff.export) and evaluation both read from here; nothing here imports evaluation or the commands."""
