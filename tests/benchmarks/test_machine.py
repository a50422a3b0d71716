"""What a report records of its run: the command that re-runs it and the commit of the checkout."""

import re

from benchmarks.machine import provenance


def test_a_report_records_the_module_command_with_its_arguments_and_the_checkouts_commit():
    recorded = provenance(["/anywhere/benchmarks/engine_speed.py", "--sizes", "s", "--vs-sim", "contact_law=1 x"])
    assert recorded["command"] == "python -m benchmarks.engine_speed --sizes s --vs-sim 'contact_law=1 x'"
    assert re.fullmatch(r"[0-9a-f]{40}", recorded["commit"])
    assert isinstance(recorded["modified"], bool)
