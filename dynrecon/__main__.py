from dynrecon.cli import main

raise SystemExit(main())
