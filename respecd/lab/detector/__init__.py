"""Detector training and evaluation: datasets, augmentation, loss, the training loop, mAP."""
