from sim_bridge.bridge import main

raise SystemExit(main())
