"""``python -m jstarid.cli``."""

from jstarid.cli import main

raise SystemExit(main())
