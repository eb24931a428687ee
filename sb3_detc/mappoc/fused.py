"""One compiled graph per gradient step: loss, gradients, clipping and the Adam update together.

With ``torch_compile=True`` and the default optimizer, :class:`~sb3_detc.mappoc.mappoc.MAPPOC`
computes the gradients with :func:`torch.func.grad_and_value` inside the compiled function
and applies :class:`torch.optim.Adam`'s update to the parameters and to the optimizer's own
state tensors (``step``, ``exp_avg``, ``exp_avg_sq``), so that ``optimizer.state_dict()``,
saving and loading, and a later switch back to ``optimizer.step()`` see exactly what
``optimizer.step()`` would have left. For networks this small, most of a gradient step is
the cost of launching kernels and running autograd and the optimizer from Python; in one
graph that cost is paid once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch as th


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

    The scaling of :func:`torch.nn.utils.clip_grad_norm_`: ``min(1, max_norm / (norm + 1e-6))``.

    :param grads: gradients of all parameters
    :param max_norm: largest joint norm
    :return: the scaled gradients
    """
    norm = th.linalg.vector_norm(th.stack([th.linalg.vector_norm(g) for g in grads]))
    scale = th.clamp(max_norm / (norm + 1e-6), max=1.0)
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
    """One Adam step in place (Kingma and Ba, Algorithm 1, as ``torch.optim.Adam`` computes it).

    ``m <- b1 m + (1 - b1) g``, ``v <- b2 v + (1 - b2) g^2``,
    ``p <- p - lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)``.

    :param params: parameters (updated in place, without autograd)
    :param grads: their gradients
    :param steps: step counters (incremented in place)
    :param exp_avgs: first moments (updated in place)
    :param exp_avg_sqs: second moments (updated in place)
    :param lr: learning rate (a 0-d tensor, so that schedules do not recompile)
    :param betas: decay rates of the moments
    :param eps: term added to the denominator
    """
    beta1, beta2 = betas
    with th.no_grad():
        for param, grad, step, exp_avg, exp_avg_sq in zip(params, grads, steps, exp_avgs, exp_avg_sqs, strict=True):
            step.add_(1)
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            bias_correction1 = 1 - beta1**step
            bias_correction2_sqrt = (1 - beta2**step).sqrt()
            denom = exp_avg_sq.sqrt() / bias_correction2_sqrt + eps
            param.sub_(lr / bias_correction1 * exp_avg / denom)
