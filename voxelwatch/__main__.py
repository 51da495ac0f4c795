"""``python -m voxelwatch ARGS`` is ``voxelwatch ARGS``."""

import sys

from voxelwatch.cli import main

sys.exit(main())
