"""Data generators used only by the tests (pyproject.toml's pytest ``pythonpath`` puts tests/ on the
import path: ``from generators import ...``)."""
