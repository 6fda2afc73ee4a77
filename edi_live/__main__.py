"""`python -m edi_live` runs the edi-live command line."""

from edi_live.cli import main

raise SystemExit(main())
