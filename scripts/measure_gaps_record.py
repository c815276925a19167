"""Writes a gap's measured CPU cost into its committed record, `data/full/<task>.progress.json`, from a trial build's
`dsrl-admin build --status --json TASK` (on standard input; TASK the first argument): see scripts/measure-gaps.sh. A
task without a record (or with one that did nothing) gets "not started" with the cost applied to its whole budget; a
committed partial build keeps its record and gains the cost, applied to what it has left. The keys are in the order
`dsrl-admin build --status --record` writes them."""
import json
import os
import sys

ORDER = ["task", "state", "done", "planned", "unit", "rate_per_second", "remaining_hours", "cpu_seconds_per_unit",
         "remaining_core_hours", "compute", "cpu"]

# `--status TASK` lists the builds TASK starts from (a warm start) before it: the named one is the record's.
listed = json.load(sys.stdin)
trial = next(p for p in listed if p["task"] == sys.argv[1]) if len(sys.argv) > 1 else listed[0]
task, unit, cost = trial["task"], trial["unit"], trial.get("cpu_seconds_per_unit")
if cost is None:
    print(f"{task}: the trial did {trial['done']} {unit}, too few to measure; nothing recorded", file=sys.stderr)
    sys.exit(0)
said = (f"the CPU cost per unit was measured on {trial['cpu']} by a trial of the build's first {trial['done']} "
        f"{unit} (not kept)")
path = os.path.join("data", "full", f"{task}.progress.json")
record = json.load(open(path)) if os.path.exists(path) else None
if record is None or record.get("done", 0) == 0:
    compute = dict(trial.get("compute") or {})
    compute["note"] = said
    record = {"task": task, "state": "not started", "done": 0, "planned": trial["planned"], "unit": unit,
              "compute": compute, "cpu": trial["cpu"]}
else:
    compute = record.setdefault("compute", {})
    compute["note"] = "; ".join(n for n in (compute.get("note", ""), said) if n)
left = max(record["planned"] - record["done"], 0)
record["cpu_seconds_per_unit"] = cost
record["remaining_core_hours"] = round(left * cost / 3600, 1)
record = {k: record[k] for k in ORDER if k in record}
with open(path, "w") as f:
    json.dump(record, f, indent=2)
    f.write("\n")
print(f"{task}: {cost} CPU s per {unit[:-1]}, {record['remaining_core_hours']} core-hours left", file=sys.stderr)
