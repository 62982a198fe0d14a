"""``python -m motorbus`` runs the command line."""

from motorbus.cli.main import main

raise SystemExit(main())
