from sim_bridge.fleet import main

raise SystemExit(main())
