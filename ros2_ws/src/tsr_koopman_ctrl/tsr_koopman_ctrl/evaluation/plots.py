"""Plots: deployments like the paper's Figs. 5-7 (tether length, in-plane angle and tension
against tau, one line per run) and log-scale error curves."""

import matplotlib
import numpy as np

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the file backend)

from tsr_sim.dynamics import LENGTH_OFFSET, THETA  # noqa: E402

from tsr_koopman_ctrl.evaluation.figures import ZONE  # noqa: E402


def plot_deployments(runs, path, title='TSR deployment'):
    """runs: {label: (tau, x, u)}; writes a three-panel PNG to path."""
    fig, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for label, (tau, x, u) in runs.items():
        axes[0].plot(tau, x[:, LENGTH_OFFSET] + 1.0, label=label)
        axes[1].plot(tau, x[:, THETA], label=label)
        axes[2].plot(tau[:len(u)], u, label=label)
    axes[0].axhspan(1.0 - ZONE, 1.0 + ZONE, color='0.85', label='1% zone')
    axes[1].axhspan(-ZONE, ZONE, color='0.85')
    axes[0].set_ylabel('tether length l = length / L')
    axes[1].set_ylabel('in-plane angle theta [rad]')
    axes[2].set_ylabel('tension u = T / (m Omega^2 L)')
    axes[2].set_xlabel('tau = Omega t')
    axes[0].set_title(title)
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc='lower right')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def log_plot(path, series, xlabel, ylabel, marker=None):
    """One PNG with a log-y line per (label, x, y) in `series`."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for label, x, y in series:
        ax.semilogy(x, y, marker=marker, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_ratios(rows, path, target=1.3, title="Settle time / minimum time at the run's swing"):
    """Grouped bars of the frontier ratio: one group per start, one bar per (law, preset) of the
    comparison rows given, a law's presets side by side in one hue (dark, then light); a run
    that did not settle is a hatched bar to the top. Lines at the frontier (1) and at `target`.
    Writes a PNG to path."""
    laws = list(dict.fromkeys(r['law'] for r in rows))
    series = sorted(dict.fromkeys((r['law'], r['preset']) for r in rows),
                    key=lambda key: laws.index(key[0]))
    starts = list(dict.fromkeys((tuple(r['start']), r['starts']) for r in rows))
    ratios = {(r['law'], r['preset'], tuple(r['start'])): r['frontier_ratio'] for r in rows}
    known = [v for v in ratios.values() if v is not None]
    top = max(known + [target]) * 1.08
    width = 0.8 / max(len(series), 1)
    fig, ax = plt.subplots(figsize=(max(8.0, 1.5 * len(starts) + 3.0), 5.0))
    colours, shade = plt.get_cmap('tab20'), {}
    for i, (law, preset) in enumerate(series):
        shade[law] = shade.get(law, -1) + 1
        values = [ratios.get((law, preset, start)) for start, _ in starts]
        x = np.arange(len(starts)) + (i - (len(series) - 1) / 2) * width
        ax.bar(x, [top if v is None else v for v in values], width,
               color=colours((2 * laws.index(law) + min(shade[law], 1)) % 20),
               label=f'{law} ({preset})',
               hatch=None if all(v is not None for v in values) else '//')
    ax.axhline(1.0, color='k', lw=0.8)
    ax.axhline(target, color='r', lw=0.8, ls='--', label=f'target {target:g}x')
    ax.set_xticks(np.arange(len(starts)))
    ax.set_xticklabels(['(' + ', '.join(f'{v:g}' for v in start) + f')\n{kind}'
                        for start, kind in starts], fontsize=7)
    ax.set_ylim(0.8, top)
    ax.set_xlabel('initial state (theta, theta\', l - 1, l\')')
    ax.set_ylabel('frontier ratio')
    ax.set_title(title)
    ax.grid(True, axis='y', alpha=0.3)
    ax.legend(fontsize=7, loc='upper left', bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
