"""Shared by the unit suites: this folder is put on ``sys.path`` so that tests in its subfolders
can import the helpers kept here (``scenes.py``: rendered scenes with known ground truth)."""

import sys
from pathlib import Path

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)
