"""``slloc eval`` and ``slloc bench``: accuracy and speed of a map and a configuration."""
