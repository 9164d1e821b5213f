"""wp.Tape over an explicit run written as NVIDIA Warp kernels, for the gradient peers of
bench/deform/ (diff_massspring_peers.py, diff_fem_peers.py): one buffer per step for x, v and
the forces (so that the tape can reverse every step), the forward pass, the loss
L = sum_i w_i . x_i(T) and its gradient with respect to the initial velocity.
Warp is imported by the caller (the peers run in their own processes)."""

from __future__ import annotations

from typing import Any


class TapeRun:
    """`step(x, v, f, x_out, v_out)` launches one step's kernels (f is zeroed before it);
    `vec` is the Warp vector type of the points (wp.vec2d or wp.vec3d)."""

    def __init__(self, wp, vec, x0, w, steps, step, device="cpu"):
        n = len(x0)
        self.wp, self.x0, self.steps, self.step, self.device = wp, x0, steps, step, device

        def buffers(count):
            return [wp.zeros(n, dtype=vec, device=device, requires_grad=True) for _ in range(count)]

        self.xs, self.vs, self.fs = buffers(steps + 1), buffers(steps + 1), buffers(steps)
        self.w = wp.array(w, dtype=vec, device=device)
        self.loss = wp.zeros(1, dtype=wp.float64, device=device, requires_grad=True)

        @wp.kernel
        def weighted_sum(x: wp.array(dtype=Any), w: wp.array(dtype=Any), loss: wp.array(dtype=wp.float64)):
            i = wp.tid()
            wp.atomic_add(loss, 0, wp.dot(w[i], x[i]))

        self._weighted_sum = weighted_sum

    def forward(self, v0) -> float:
        """Runs the steps from (x0, v0); returns the loss."""
        self._launch(v0)
        return float(self.loss.numpy()[0])

    def _launch(self, v0):
        self.xs[0].assign(self.x0)
        self.vs[0].assign(v0)
        self.loss.zero_()
        for t in range(self.steps):
            self.fs[t].zero_()
            self.step(self.xs[t], self.vs[t], self.fs[t], self.xs[t + 1], self.vs[t + 1])
        self.wp.launch(self._weighted_sum, dim=len(self.x0), inputs=[self.xs[self.steps], self.w],
                       outputs=[self.loss], device=self.device)

    def gradient(self, v0):
        """dL/dv0 by a tape over the forward pass (the array of v0's shape)."""
        tape = self.wp.Tape()
        with tape:
            self._launch(v0)
        tape.backward(self.loss)
        out = self.vs[0].grad.numpy().copy()
        tape.zero()
        return out
