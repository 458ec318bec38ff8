"""Local feature matchers: a protocol, and one module per backend."""
