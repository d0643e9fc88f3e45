#!/usr/bin/env python3
"""Summarise a fusion campaign database (issue 30): per condition, the learning run's
(combine phase's, or the one-phase run's) final task %, its first step at 80 %, and the
fixed test's final % (the trial's own final_task_pct when the campaign samples).

usage: scripts/fusion-summary.py DB [THRESHOLD]
"""
import sqlite3, statistics, sys

db = sys.argv[1]
thr = float(sys.argv[2]) if len(sys.argv) > 2 else 80.0
c = sqlite3.connect(db)
rows = c.execute(
    "select id, condition, task, seed, final_task_pct, wall_seconds, stage_wall_seconds "
    "from trials where status='done' order by condition, task, seed").fetchall()
by = {}
for tid, cond, task, seed, fixed_final, wall, stage_wall in rows:
    curve = c.execute("select step, task_pct from learning_steps where trial=? order by step", (tid,)).fetchall()
    if not curve:  # no separate learning curve: the trial's own steps
        curve = c.execute("select step, task_pct from steps where trial=? order by step", (tid,)).fetchall()
    final = curve[-1][1] if curve else float('nan')
    t80 = next((s for s, p in curve if p >= thr), None)
    by.setdefault((cond, task), []).append((seed, final, t80, fixed_final, wall))

def q(v):
    return f"{statistics.median(v):.1f}" if v else "-"

print(f"| condition | task | seeds | learning final %: median (range) | learning ≥ {thr:.0f} % | "
      f"first step at {thr:.0f} %: median (range) | fixed top 50 % final: median / mean / ≥ {thr:.0f} % | wall s / trial |")
print("|---|---|---|---|---|---|---|---|")
for (cond, task), v in by.items():
    finals = [x[1] for x in v]
    t80s = [x[2] for x in v if x[2] is not None]
    fixed = [x[3] for x in v if x[3] is not None]
    reach = len(t80s)
    t = f"{statistics.median(t80s):.0f} ({min(t80s)}–{max(t80s)})" if t80s else "never"
    fx = f"{q(fixed)} / {statistics.mean(fixed):.1f} / {sum(f >= thr for f in fixed)}" if fixed else "-"
    print(f"| {cond} | {task} | {len(v)} | {q(finals)} ({min(finals):.0f}–{max(finals):.0f}) | {reach}/{len(v)} | {t} | {fx} | {statistics.mean(x[4] for x in v):.0f} |")
if "-v" in sys.argv:
    for (cond, task), v in by.items():
        print(cond, task, "learning finals:", [round(x[1]) for x in v], "fixed:", [None if x[3] is None else round(x[3]) for x in v])
