"""``python -m vggt_slam_pp`` is the same as the ``vggt-slam-pp`` command."""

import sys

from vggt_slam_pp.cli.main import main

sys.exit(main())
