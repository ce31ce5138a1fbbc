"""Drivers over the pipeline: optimizers, sequences of windows, motion segmentation."""
