"""``python -m sffscan.pipeline.cli``: the ``sffscan`` command."""

from sffscan.pipeline.cli.main import main

raise SystemExit(main())
