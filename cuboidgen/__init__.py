"""Synthetic sample generator daemon (producer half of cuboid-fit)."""
