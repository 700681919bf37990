import sys

from driver_bridge.node import main

sys.exit(main())
