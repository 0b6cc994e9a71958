"""Where the package, its bundled data and the repository's neighbours are on disk."""

from __future__ import annotations

from pathlib import Path

PACKAGE = Path(__file__).resolve().parent
DATA = PACKAGE / "data"  # bundled with the package (motions, PCM calibration, reference crops)
REPO = PACKAGE.parent  # a source checkout: config/, models/, out/ live here
SHARED_DATA = REPO.parent / "shared" / "data"  # the lab's real datasets beside the checkout
