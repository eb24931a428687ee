"""One compiled graph per gradient step: loss, gradients, clipping and the Adam update together.

With ``torch_compile=True`` and the default optimizer, :class:`~sb3_detc.mappoc.mappoc.MAPPOC`
computes the gradients with :func:`torch.func.grad_and_value` inside the compiled function
and applies :class:`torch.optim.Adam`'s update (its functional form) to the parameters and to
the optimizer's own state tensors (``step``, ``exp_avg``, ``exp_avg_sq``), so that ``optimizer.state_dict()``,
saving and loading, and a later switch back to ``optimizer.step()`` see exactly what
``optimizer.step()`` would have left. For networks this small, most of a gradient step is
the cost of launching kernels and running autograd and the optimizer from Python; in one
graph that cost is paid once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch as th
from torch.optim.adam import adam


def fusable_adam(optimizer: th.optim.Optimizer) -> bool:
    """Whether :func:`adam_update_` reproduces ``optimizer.step()``.

    True for :class:`torch.optim.Adam` with one parameter group, without weight decay,
    AMSGrad, maximisation, or differentiable or tensor-valued hyperparameters.

    :param optimizer: the policy's optimizer
    """
    if type(optimizer) is not th.optim.Adam or len(optimizer.param_groups) != 1:
        return False
    group = optimizer.param_groups[0]
    return (
        group["weight_decay"] == 0
        and not group["amsgrad"]
        and not group["maximize"]
        and not group["differentiable"]
        and not any(isinstance(group[key], th.Tensor) for key in ("lr", "betas", "eps"))
    )


def adam_state(optimizer: th.optim.Optimizer) -> tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor]]:
    """The optimizer's ``step``, ``exp_avg`` and ``exp_avg_sq`` of every parameter, created if missing.

    New state has the form ``torch.optim.Adam`` gives it before its first step (zero moments,
    a float32 step counter on the parameter's device).

    :param optimizer: an optimizer for which :func:`fusable_adam` holds
    :return: step counters, first moments, second moments, in the order of the parameters
    """
    steps, exp_avgs, exp_avg_sqs = [], [], []
    for param in optimizer.param_groups[0]["params"]:
        state = optimizer.state[param]
        if not state:
            state["step"] = th.zeros((), dtype=th.float32, device=param.device)
            state["exp_avg"] = th.zeros_like(param, memory_format=th.preserve_format)
            state["exp_avg_sq"] = th.zeros_like(param, memory_format=th.preserve_format)
        steps.append(state["step"])
        exp_avgs.append(state["exp_avg"])
        exp_avg_sqs.append(state["exp_avg_sq"])
    return steps, exp_avgs, exp_avg_sqs


def clip_by_total_norm(grads: Sequence[th.Tensor], max_norm: float) -> list[th.Tensor]:
    """Scale gradients so that their joint L2 norm is at most ``max_norm``.

    The scaling of :func:`torch.nn.utils.clip_grad_norm_`, ``min(1, max_norm / (norm + 1e-6))``,
    for gradients that are not stored in ``.grad``.

    :param grads: gradients of all parameters
    :param max_norm: largest joint norm
    :return: the scaled gradients
    """
    scale = th.clamp(max_norm / (th.nn.utils.get_total_norm(grads) + 1e-6), max=1.0)
    return [g * scale for g in grads]


def adam_update_(
    params: Sequence[th.Tensor],
    grads: Sequence[th.Tensor],
    steps: Sequence[th.Tensor],
    exp_avgs: Sequence[th.Tensor],
    exp_avg_sqs: Sequence[th.Tensor],
    lr: th.Tensor,
    betas: tuple[float, float],
    eps: float,
) -> None:
    """One step of :class:`torch.optim.Adam` in place, through its functional form (``torch.optim.adam.adam``).

    ``capturable=True`` keeps the step counters and the bias corrections as tensors, so that
    the step compiles into the same graph as the gradients.

    :param params: parameters (updated in place, without autograd)
    :param grads: their gradients
    :param steps: step counters (incremented in place)
    :param exp_avgs: first moments (updated in place)
    :param exp_avg_sqs: second moments (updated in place)
    :param lr: learning rate (a 0-d tensor, so that schedules do not recompile)
    :param betas: decay rates of the moments
    :param eps: term added to the denominator
    """
    with th.no_grad():
        adam(
            list(params),
            list(grads),
            list(exp_avgs),
            list(exp_avg_sqs),
            [],
            list(steps),
            foreach=False,
            capturable=True,
            amsgrad=False,
            beta1=betas[0],
            beta2=betas[1],
            lr=lr,
            weight_decay=0.0,
            eps=eps,
            maximize=False,
        )
