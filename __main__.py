from scancell.cli import main

raise SystemExit(main())
