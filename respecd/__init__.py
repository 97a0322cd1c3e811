"""respecd: adaptive multispectral sensing daemon (the ReSPEC method)."""

__version__ = "0.1.0"
