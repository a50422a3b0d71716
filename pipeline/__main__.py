"""`python -m pipeline <command> ...`: the `kforge` command line without the installed script (e.g. in Ray jobs)."""

from pipeline.cli import main

main()
