"""Test set-up: the repository's packages importable without installing trifuse, and the
location of the shared data (real images with reference results)."""

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# shared/ lies beside the repository, on the developers' machines and in CI;
# TRIFUSE_SHARED_DIR points elsewhere.
SHARED_DIR = Path(os.environ.get("TRIFUSE_SHARED_DIR", ROOT.parent / "shared"))
OPENCV_LEFT_9X6 = SHARED_DIR / "data" / "opencv-left-9x6"
