"""neuralmap: neural terrain maps and batched terrain-aided navigation in PyTorch."""

__version__ = "0.1.0"
