"""Device URLs and the one registry that opens camera sources and servo buses by URL scheme."""
