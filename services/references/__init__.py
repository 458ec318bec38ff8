"""What a reference store gives the engine (store.py) and the decoded features kept between
requests (cache.py)."""
