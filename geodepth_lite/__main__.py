from geodepth_lite.cli import main

raise SystemExit(main())
