"""`python -m kforge <command> ...`: the `kforge` command line without the installed script (e.g. in Ray jobs)."""

from kforge.pipeline.cli import main

main()
