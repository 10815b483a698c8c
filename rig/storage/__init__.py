"""Recorded sequences on disk (docs/sequence-format.md).

layout     the folder's file names and sequence.json        netpbm     the image files
recorder   writes FrameSets as they arrive                   index      reads index.jsonl, crash damage and all
validate   `rig record validate`                             repair     `rig record repair`: keeps every good set
dataset    reads a take for training and evaluation
"""
