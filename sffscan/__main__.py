"""``python -m sffscan``: the ``sffscan`` command."""

from sffscan.pipeline.cli.main import main

raise SystemExit(main())
