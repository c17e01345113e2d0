"""psdfactory: synthetic particle-bed images with PSD labels, and CNNs that read them."""

__version__ = "0.1.0"


class PsdError(Exception):
    """An error with a message meant for the user (bad input, failed quality check, ...)."""
