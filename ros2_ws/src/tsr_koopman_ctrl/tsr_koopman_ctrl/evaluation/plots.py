"""Plots: deployments like the paper's Figs. 5-7 (tether length, in-plane angle and tension
against tau, one line per run) and log-scale error curves."""

import matplotlib

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
