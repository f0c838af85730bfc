from metarig.cli import main

raise SystemExit(main())
