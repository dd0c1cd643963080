"""PolySfT: shape-from-template on image sequences with oriented n-jet patches."""
