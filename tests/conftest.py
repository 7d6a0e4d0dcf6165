"""Shared pytest setup. tests/ is a package: shared helpers import as tests.<module>
(e.g. tests.synthetic_scenes), and the repository root is on sys.path (pyproject pythonpath)."""
