"""MAPPOC's gradient step: eager, or fused into one compiled graph.

:class:`GradientStep` is PyTorch's usual step: the loss, ``backward()``, optional gradient
clipping and ``optimizer.step()``; it can stop an update early when the control policy's
approximate KL divergence grows too large (``target_kl``).

:class:`FusedGradientStep` computes the gradients with :func:`torch.func.grad_and_value`
inside one compiled function and applies :class:`torch.optim.Adam`'s update (its functional
form) to the parameters and to the optimizer's own state tensors (``step``, ``exp_avg``,
``exp_avg_sq``), so that ``optimizer.state_dict()``, saving and loading, and a later switch
back to ``optimizer.step()`` see exactly what ``optimizer.step()`` would have left. For
networks this small, most of a gradient step is the cost of launching kernels and running
autograd and the optimizer from Python; in one graph that cost is paid once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch as th
from torch.optim.adam import adam

from sb3_detc.mappoc.losses import STEP_STATS, MAPPOCLoss, UpdateInputs

#: Position of the control policy's approximate KL divergence in a step's statistics.
KL_PI = STEP_STATS.index("kl_pi")


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


class GradientStep:
    """The loss of a minibatch, ``backward()``, optional gradient clipping and ``optimizer.step()``.

    :param loss: the loss module
    :param optimizer: the optimizer of the loss's policy
    :param max_grad_norm: largest joint gradient norm (None: no clipping)
    :param target_kl: skip the step, and tell the update to stop, when the control policy's
        approximate KL divergence exceeds ``1.5 * target_kl`` (None: never)
    :param compile_loss: evaluate the loss with :func:`torch.compile`
    """

    def __init__(
        self,
        loss: MAPPOCLoss,
        optimizer: th.optim.Optimizer,
        max_grad_norm: float | None,
        target_kl: float | None,
        compile_loss: bool = False,
    ) -> None:
        self.loss = loss
        self.optimizer = optimizer
        self.max_grad_norm = max_grad_norm
        self.target_kl = target_kl
        self.loss_fn = th.compile(loss) if compile_loss else loss

    def __call__(self, update: UpdateInputs, idx: th.Tensor) -> tuple[th.Tensor, bool]:
        """One step on the minibatch ``idx``.

        :param update: what the loss needs of the rollout and the update (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the step's statistics (:data:`STEP_STATS`), and whether the step was applied
            (False: the update should stop)
        """
        loss, step_stats = self.loss_fn(update, idx)
        if self.target_kl is not None and step_stats[KL_PI].item() > 1.5 * self.target_kl:
            return step_stats, False
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.max_grad_norm is not None:
            th.nn.utils.clip_grad_norm_(self.loss.policy.parameters(), self.max_grad_norm)
        self.optimizer.step()
        return step_stats, True


class FusedGradientStep:
    """:class:`GradientStep` without early stopping as one compiled function (see the module).

    Only for an optimizer for which :func:`fusable_adam` holds.

    :param loss: the loss module
    :param optimizer: the optimizer of the loss's policy
    :param max_grad_norm: largest joint gradient norm (None: no clipping)
    :raises ValueError: if :func:`fusable_adam` does not hold for ``optimizer``
    """

    def __init__(self, loss: MAPPOCLoss, optimizer: th.optim.Optimizer, max_grad_norm: float | None) -> None:
        if not fusable_adam(optimizer):
            raise ValueError("the fused gradient step reproduces plain torch.optim.Adam only.")
        self.loss = loss
        self.optimizer = optimizer
        self.max_grad_norm = max_grad_norm
        names = {id(param): name for name, param in loss.named_parameters()}
        #: the loss module's names of the optimizer's parameters, in the optimizer's order
        self.names = [names[id(param)] for param in optimizer.param_groups[0]["params"]]
        self.compiled = th.compile(self.step)

    def __call__(self, update: UpdateInputs, idx: th.Tensor) -> tuple[th.Tensor, bool]:
        """One step on the minibatch ``idx``, always applied.

        :param update: what the loss needs of the rollout and the update (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the step's statistics (:data:`STEP_STATS`), and True
        """
        params = self.optimizer.param_groups[0]["params"]
        lr = th.tensor(self.optimizer.param_groups[0]["lr"], device=params[0].device)
        # Scheduled numbers as tensors: a float would be compiled in, and each new value recompile the step.
        scalars = {
            name: th.tensor(getattr(update, name), dtype=th.float64, device=params[0].device)
            for name in ("clip_pi", "clip_mu", "zeta")
        }
        adam_tensors = (params, *adam_state(self.optimizer))
        return self.compiled(adam_tensors, self.names, lr, update._replace(**scalars), idx), True

    def step(
        self,
        adam_tensors: tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor], list[th.Tensor]],
        names: list[str],
        lr: th.Tensor,
        update: UpdateInputs,
        idx: th.Tensor,
    ) -> th.Tensor:
        """The function that is compiled: loss, gradients, clipping and the Adam update.

        :param adam_tensors: the optimizer's parameters and their ``step``, ``exp_avg`` and ``exp_avg_sq``
        :param names: the names of the parameters in the loss module
        :param lr: learning rate (0-d tensor)
        :param update: what the loss needs (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the statistics named in :data:`STEP_STATS`
        """
        params, steps, exp_avgs, exp_avg_sqs = adam_tensors

        def loss_of(values: tuple[th.Tensor, ...]) -> tuple[th.Tensor, th.Tensor]:
            return th.func.functional_call(self.loss, dict(zip(names, values, strict=True)), (update, idx))

        grads, (_, step_stats) = th.func.grad_and_value(loss_of, has_aux=True)(tuple(params))
        if self.max_grad_norm is not None:
            grads = clip_by_total_norm(grads, self.max_grad_norm)
        group = self.optimizer.param_groups[0]
        adam_update_(params, grads, steps, exp_avgs, exp_avg_sqs, lr, group["betas"], group["eps"])
        return step_stats
