from agent.shell.node import main

raise SystemExit(main())
