from agent.node import main

raise SystemExit(main())
