"""``python -m skyloop`` runs the ``skyloop`` command."""

from skyloop.cli import main

raise SystemExit(main())
