"""Geometry shared by the stages: transforms, rotation vectors, similarity fits, look-at, camera visibility."""
