"""A PyTorch bridge for :mod:`kinema.diff`: a simulation rollout as a differentiable function of
tensors, so that losses, optimisers and neural controllers can be written in PyTorch.

    import torch
    v0 = torch.zeros(n, 2, dtype=torch.float64, requires_grad=True)
    out = km.torch.rollout(sim, 100, 1e-3, {"v": v0})
    loss = ((out["x"] - target) ** 2).sum()
    loss.backward()            # v0.grad holds dL/dv0, through the whole run

Each call sets the given inputs on the simulation (state arrays and parameters), runs
:func:`kinema.diff.rollout` with respect to the inputs that require gradients (and the controls,
when they do), and returns the final state as float64 tensors. Rollouts chain: feed one call's
outputs into the next (a controller's per-step actions are a loop of one-step rollouts). The
simulation is left in the final state, as ``km.diff.rollout`` leaves it. Requires the optional
``torch`` extra (``pip install kinema[torch]``).
"""

from __future__ import annotations

try:
    import torch as _torch
except ImportError as e:  # pragma: no cover - exercised only without the extra
    raise ImportError("kinema.torch needs PyTorch: pip install 'kinema[torch]'") from e

import numpy as np

from kinema import diff as _diff

__all__ = ["rollout"]


def _to_numpy(t, name):
    if not isinstance(t, _torch.Tensor):
        raise ValueError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    return t.detach().to(device="cpu", dtype=_torch.float64).contiguous().numpy().copy()


class _Rollout(_torch.autograd.Function):
    @staticmethod
    def forward(ctx, spec, *tensors):
        sim, names, steps, dt, has_controls, outputs, checkpoints, options = spec
        inputs = tensors[:len(names)]
        controls = tensors[len(names)] if has_controls else None
        for name, t in zip(names, inputs):
            sim._diff_set(name, _to_numpy(t, f"inputs[{name!r}]"))
        wrt = [name for name, t in zip(names, inputs) if t.requires_grad]
        if controls is not None and controls.requires_grad:
            wrt.append("controls")
        control_array = None if controls is None else _to_numpy(controls, "controls")
        if wrt:
            run = _diff.rollout(sim, steps, dt, wrt=tuple(wrt), controls=control_array,
                                checkpoints=checkpoints, **options)
            values = run.outputs
        else:
            run = None
            for k in range(steps):
                sim._diff_step(dt, None if control_array is None else control_array[k], options)
            state = sim.state()
            values = {name: np.array(state[name], copy=True) for name in outputs}
        ctx.run = run
        ctx.outputs = outputs
        ctx.input_meta = [(t.dtype, t.device, t.shape) for t in tensors]
        ctx.wrt = wrt
        ctx.names = names
        ctx.has_controls = has_controls
        return tuple(_torch.from_numpy(np.array(values[name], copy=True)) for name in outputs)

    @staticmethod
    def backward(ctx, *grad_outputs):
        result = [None] * len(ctx.input_meta)
        if ctx.run is None:
            return (None, *result)
        grads = {name: g.detach().to(dtype=_torch.float64).cpu().numpy()
                 for name, g in zip(ctx.outputs, grad_outputs) if g is not None}
        got = ctx.run.backward(grads)
        slots = list(ctx.names) + (["controls"] if ctx.has_controls else [])
        for k, name in enumerate(slots):
            if name in got:
                dtype, device, shape = ctx.input_meta[k]
                value = np.asarray(got[name], dtype=np.float64).reshape(tuple(shape))
                result[k] = _torch.from_numpy(value).to(dtype=dtype, device=device)
        return (None, *result)


def rollout(sim, steps, dt, inputs=None, *, controls=None, outputs=None, checkpoints=None,
            **step_options):
    """Runs ``sim`` for ``steps`` steps of ``dt`` from ``inputs`` and returns the final state.

    Args:
        sim: a differentiable kinema simulation (see :mod:`kinema.diff`).
        steps, dt: the run, as in :func:`kinema.diff.rollout`.
        inputs: dict name -> tensor: state arrays ("x", "v", ...) and parameters (names in
            ``sim.parameters``) to set before the run; gradients flow to those that require them.
        controls: None or a tensor of shape (steps, *control_shape) (per-step forcing).
        outputs: names of the state arrays to return (default: all differentiable ones).
        checkpoints: as in :func:`kinema.diff.rollout`.

    Returns:
        dict name -> float64 tensor of the state after the run.
    """
    inputs = {} if inputs is None else dict(inputs)
    for name in inputs:
        if not isinstance(name, str):
            raise ValueError(f"inputs: expected names (str) as keys, got {name!r}")
    state_names = tuple(sim._diff_state_names)
    known = state_names + tuple(sim.parameters)
    for name in inputs:
        if name not in known:
            raise ValueError(f"inputs: unknown name {name!r}; expected one of {known}")
    outputs = state_names if outputs is None else tuple(outputs)
    for name in outputs:
        if name not in state_names:
            raise ValueError(f"outputs: unknown name {name!r}; expected one of {state_names}")
    names = tuple(inputs)
    tensors = [inputs[n] for n in names]
    for name, t in zip(names, tensors):
        if not isinstance(t, _torch.Tensor):
            raise ValueError(f"inputs[{name!r}]: expected a torch.Tensor, got {type(t).__name__}")
    if controls is not None:
        if not isinstance(controls, _torch.Tensor):
            raise ValueError(f"controls: expected a torch.Tensor, got {type(controls).__name__}")
        tensors.append(controls)
    steps, dt = _diff._check_run(steps, dt)
    spec = (sim, names, steps, dt, controls is not None, outputs, checkpoints, step_options)
    values = _Rollout.apply(spec, *tensors)
    return dict(zip(outputs, values))
