"""Maps on the globe: WGS84 geodesy, a map's similarity to the local East-North-Up frame, and
OGC GeoPose answers."""
