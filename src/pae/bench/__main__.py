"""`python -m pae.bench` (what `make bench` runs)."""

from pae.bench.cli import main

raise SystemExit(main())
