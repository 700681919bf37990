from sim_bridge.lab.cli import main

raise SystemExit(main())
