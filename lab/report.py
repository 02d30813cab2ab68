"""The deployment table: one row per run, from the figures `evaluation.run_figures` computed
out of the bag (plus the controller's compute times and counters, also from the bag)."""

import json
import os

from tsr_sim import dynamics


def settle_cell(row):
    if row['settle_tau'] is not None:
        return f"{row['settle_tau']:.2f}"
    if row['halted']:
        return f"left the domain at tau {row['halt_tau']:.2f}"
    if row['steps'] < row['planned_steps']:
        return f"stopped at step {row['steps']}"
    return 'not reached'


def summary_table(rows):
    def fmt(v, digits=2):
        return '-' if v is None else f'{v:.{digits}f}'

    lines = ['| controller | x0 | settle tau (1% zone) | final l | theta range [rad] | '
             'l overshoot | max u | integral u dtau | compute median / p99 [us] | '
             'frontier tau | ratio |', '|---|---|---|---|---|---|---|---|---|---|---|']
    for r in rows:
        final_l = r['final_state'][dynamics.LENGTH_OFFSET] + 1.0
        lines.append(f"| {r['controller']} | {r['x0']} | {settle_cell(r)} | {final_l:.3f} | "
                     f"[{r['theta_min']:.3f}, {r['theta_max']:.3f}] | "
                     f"{r['length_overshoot']:.4f} | {r['tension_max']:.3f} | "
                     f"{r['tension_integral']:.2f} | {fmt(r['compute_median_us'], 0)} / "
                     f"{fmt(r['compute_p99_us'], 0)} | {fmt(r['frontier_tau'], 1)} | "
                     f"{fmt(r['frontier_ratio'])} |")
    return '\n'.join(lines)


def write_results(directory, name, data, text, indent=1):
    """<name>.json (`data`) and <name>.md (`text`) in `directory`, made if needed: how every
    tool leaves its results."""
    os.makedirs(directory, exist_ok=True)
    with open(os.path.join(directory, f'{name}.json'), 'w') as f:
        json.dump(data, f, indent=indent)
    with open(os.path.join(directory, f'{name}.md'), 'w') as f:
        f.write(text)


def write_report(run_dir, rows):
    """summary.json and summary.md in run_dir; prints the table."""
    table = summary_table(rows)
    write_results(run_dir, 'summary', rows, table + '\n', indent=2)
    print(table)
    print(f'[deploy] plots and summary in {run_dir}/', flush=True)
