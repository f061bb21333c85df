"""Simulator of a calibration cell: a bag plus its ground truth."""
