"""Shared pytest setup: tests/ is on sys.path (rootdir conftest), so helpers like
synthetic_scenes import by name."""
