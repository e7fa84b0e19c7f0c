"""Data generators used only by the tests (conftest.py puts tests/ on sys.path: ``from generators import ...``)."""
