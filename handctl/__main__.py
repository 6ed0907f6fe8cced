"""``python -m handctl`` is the ``handctl`` command."""

from handctl.cli import main

raise SystemExit(main())
