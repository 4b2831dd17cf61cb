from cmnav.cli import main

raise SystemExit(main())
