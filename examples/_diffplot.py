"""What the gradient examples (examples/diff_*.py) share: the Adam optimiser and the plot of the
loss against the iteration. Not a program: the examples import it (from any working directory,
by their own folder)."""

import numpy as np


class Adam:
    """Adam (Kingma and Ba 2015) with beta1 = 0.9, beta2 = 0.999: ``step(params, grads)`` moves
    each array of ``params`` in place by -lr m_hat / (sqrt(v_hat) + eps), m and v the running
    means of its gradient and squared gradient, bias-corrected."""

    def __init__(self, lr, eps=1e-12):
        self.lr, self.eps = lr, eps
        self.t = 0
        self.m = self.v = None

    def step(self, params, grads):
        self.t += 1
        if self.m is None:
            self.m = [np.zeros_like(g) for g in grads]
            self.v = [np.zeros_like(g) for g in grads]
        for p, g, m, v in zip(params, grads, self.m, self.v):
            m[...] = 0.9 * m + 0.1 * g
            v[...] = 0.999 * v + 0.001 * g * g
            p -= self.lr * (m / (1 - 0.9 ** self.t)) / (np.sqrt(v / (1 - 0.999 ** self.t)) + self.eps)


def pyplot():
    """matplotlib.pyplot on the Agg backend (files only, no window)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_loss(path, losses, ylabel, title, *, log=True, first=0, style="o-"):
    """The loss against the iteration (numbered from ``first``), log scale unless ``log`` is
    False, written to ``path``."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5, 3.5))
    (ax.semilogy if log else ax.plot)(np.arange(first, first + len(losses)), losses, style, ms=3)
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
