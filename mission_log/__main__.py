import sys

from mission_log.cli import main

sys.exit(main())
