"""Placing an estimate on the map: the position record, tiled and whole-body searches, fits on the map itself."""
