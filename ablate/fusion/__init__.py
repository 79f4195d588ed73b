"""Fusion operators and fusion stages."""
