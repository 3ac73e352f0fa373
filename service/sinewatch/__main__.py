from sinewatch.cli import main

raise SystemExit(main())
