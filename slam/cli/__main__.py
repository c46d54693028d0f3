"""``python -m slam.cli`` = ``dynslam``."""
import sys

from slam.cli import main

sys.exit(main())
