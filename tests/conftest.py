"""The repository root on sys.path: some tests import helpers of others
(``from tests.test_ukf_numba import ...``), which otherwise worked only when
an earlier test in the same worker had put the root there."""

import sys
from pathlib import Path

ROOT = str(Path(__file__).resolve().parents[1])
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
