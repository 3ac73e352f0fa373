from sinewatch.apps.cli import main

raise SystemExit(main())
