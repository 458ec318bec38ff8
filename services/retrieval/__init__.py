"""Image retrieval: global descriptors and nearest-neighbour search over a map."""
