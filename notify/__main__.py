"""``python -m common.notify ARGS`` is ``voxelwatch notify ARGS``."""

import sys

from common.cli import main

sys.exit(main(["notify", *sys.argv[1:]]))
