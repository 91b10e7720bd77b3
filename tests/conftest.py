"""pytest puts this folder on the import path: the tests import their shared helpers from
``tests/shared.py``."""
