"""Shipped YAML profiles, installed as ``respecd.profiles`` so a bare ``respecd`` finds its default."""
