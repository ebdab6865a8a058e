"""``python -m skyloop`` runs the ``skyloop`` command."""

from skyloop.cli.main import main

raise SystemExit(main())
