"""Perception: the fusion detector, cross-modal alignment and contribution attribution."""
