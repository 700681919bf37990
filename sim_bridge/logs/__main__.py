import sys

from sim_bridge.logs.cli import main

sys.exit(main())
