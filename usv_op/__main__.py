from usv_op.cli import main

raise SystemExit(main())
