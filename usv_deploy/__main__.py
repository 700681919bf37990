import sys

from usv_deploy.cli import main

sys.exit(main())
