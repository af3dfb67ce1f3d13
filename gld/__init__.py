"""gld: learning dense depth from two views and optical flow with very sparse supervision."""

__version__ = "0.1.0"
