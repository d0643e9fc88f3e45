#!/usr/bin/env python3
"""Least-squares power and efficiency slopes per series level (e.g. mutation = fixed|stress)
from the points.csv that `geese report DB` writes: the report fits one line per task over
all series, the stress-mutation comparison (issue 30.3) needs one per rule.
Usage: scripts/slopes_by_series.py REPORT_DIR/points.csv"""
import csv, sys
def ols(xs, ys):
    n=len(xs); mx=sum(xs)/n; my=sum(ys)/n
    sxx=sum((x-mx)**2 for x in xs)
    if sxx==0: return None
    return sum((x-mx)*(y-my) for x,y in zip(xs,ys))/sxx
rows=list(csv.DictReader(open(sys.argv[1])))

out={}
for r in rows:
    k=(r['task'], r['series'])
    out.setdefault(k,[]).append(r)
print(f"{'task':9} {'rule':7} {'n':>3} {'power slope/unit':>17} {'eff slope/unit':>15} {'power slope/pos':>16} {'eff slope/pos':>14} {'power mean':>10} {'eff mean':>9}")
for (task, series), rs in sorted(out.items()):
    xs=[float(r['x']) for r in rs]; xp=[float(r['x_position']) for r in rs]
    p=[float(r['power']) for r in rs]; e=[float(r['efficiency']) for r in rs]
    f=lambda v: 'n/a' if v is None else f'{v:.5f}'
    print(f"{task:9} {series:7} {len(rs):>3} {f(ols(xs,p)):>17} {f(ols(xs,e)):>15} {f(ols(xp,p)):>16} {f(ols(xp,e)):>14} {sum(p)/len(p):>10.2f} {sum(e)/len(e):>9.2f}")
