"""Local feature extractors: a protocol, and one module per backend."""
