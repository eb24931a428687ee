"""MAPPOC's gradient step: eager, or fused into one compiled graph.

:class:`GradientStep` is PyTorch's usual step: the loss, ``backward()``, optional gradient
clipping and ``optimizer.step()``; it can stop an update early when the control policy's
approximate KL divergence grows too large (``target_kl``).

:class:`FusedGradientStep` computes the gradients with :func:`torch.func.grad_and_value`
inside one compiled function and applies :class:`torch.optim.Adam`'s arithmetic
(:func:`adam_update_`) to the parameters and to the optimizer's own state tensors (``step``, ``exp_avg``,
``exp_avg_sq``), so that ``optimizer.state_dict()``, saving and loading, and a later switch
back to ``optimizer.step()`` see exactly what ``optimizer.step()`` would have left. For
networks this small, most of a gradient step is the cost of launching kernels and running
autograd and the optimizer from Python; in one graph that cost is paid once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch as th

from sb3_detc.mappoc.losses import STEP_STATS, MAPPOCLoss, UpdateInputs

#: Position of the control policy's approximate KL divergence in a step's statistics.
KL_PI = STEP_STATS.index("kl_pi")
#: Steps of the fused gradient step whose Adam scalars are computed together (:func:`adam_scalars`).
ADAM_ROWS = 64


def fusable_adam(optimizer: th.optim.Optimizer) -> bool:
    """Whether :func:`adam_update_` reproduces ``optimizer.step()``.

    True for :class:`torch.optim.Adam` with one parameter group, without weight decay,
    AMSGrad, maximisation, or differentiable or tensor-valued hyperparameters.

    :param optimizer: the policy's optimizer
    :return: True if the fused update can replace the optimizer's step
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


def adam_scalars(
    steps: Sequence[th.Tensor], lr: float, betas: tuple[float, float], n_steps: int = 1
) -> tuple[th.Tensor, th.Tensor]:
    """Every parameter's step size and square root of the second bias correction in the coming Adam steps.

    What ``optimizer.step()`` computes from Python floats (in double precision) before it
    touches a tensor. Computed outside the compiled step and passed in: inside, the compiler
    inlines scalar arithmetic into the loops over parameter elements and evaluates two powers
    per eight elements.

    :param steps: step counters before the first of these steps, one per parameter
    :param lr: learning rate
    :param betas: decay rates of the moments
    :param n_steps: number of coming steps
    :return: ``lr / (1 - beta1 ** t)`` and ``sqrt(1 - beta2 ** t)``, float32, shaped
        (n_steps, parameters): row ``k`` for step ``k``, with ``t`` the counter after that step
    """
    ahead = th.arange(1, n_steps + 1, dtype=th.float64, device=steps[0].device)
    t = th.stack(list(steps)).double() + ahead[:, None]
    step_sizes = lr / (1 - betas[0] ** t)
    bias_correction2_sqrts = (1 - betas[1] ** t).sqrt()
    return step_sizes.float(), bias_correction2_sqrts.float()


def adam_update_(
    params: Sequence[th.Tensor],
    grads: Sequence[th.Tensor],
    adam_tensors: tuple[Sequence[th.Tensor], Sequence[th.Tensor], Sequence[th.Tensor]],
    step_sizes: th.Tensor,
    bias_correction2_sqrts: th.Tensor,
    betas: tuple[float, float],
    eps: float,
) -> None:
    """One step of :class:`torch.optim.Adam` (without weight decay or AMSGrad) in place.

    The arithmetic of ``optimizer.step()`` on one parameter, with its scalars from
    :func:`adam_scalars`.

    :param params: parameters (updated in place, without autograd)
    :param grads: their gradients
    :param adam_tensors: step counters (incremented in place), first moments and second
        moments (updated in place), in the order of ``params``
    :param step_sizes: every parameter's step size (:func:`adam_scalars`)
    :param bias_correction2_sqrts: every parameter's square root of the second bias correction
    :param betas: decay rates of the moments
    :param eps: term added to the denominator
    """
    steps, exp_avgs, exp_avg_sqs = adam_tensors
    with th.no_grad():
        for i, (param, grad, step, exp_avg, exp_avg_sq) in enumerate(
            zip(params, grads, steps, exp_avgs, exp_avg_sqs, strict=True)
        ):
            step.add_(1)
            exp_avg.lerp_(grad, 1 - betas[0])
            exp_avg_sq.mul_(betas[1]).addcmul_(grad, grad, value=1 - betas[1])
            denom = (exp_avg_sq.sqrt() / bias_correction2_sqrts[i]).add_(eps)
            param.sub_(step_sizes[i] * exp_avg / denom)


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
        #: whether the next call compiles the loss (see :meth:`warm_up`)
        self.needs_warm_up = compile_loss

    def warm_up(self, update: UpdateInputs, idx: th.Tensor) -> None:
        """Compile the loss and its backward pass now (its gradients are discarded; parameters and optimizer stay).

        :param update: inputs of the shapes and settings of the coming update (any values)
        :param idx: indices of a minibatch
        """
        loss, _ = self.loss_fn(update, idx)
        loss.backward()
        self.optimizer.zero_grad(set_to_none=True)
        self.needs_warm_up = False

    def __call__(self, update: UpdateInputs, idx: th.Tensor) -> tuple[th.Tensor, bool]:
        """One step on the minibatch ``idx``.

        :param update: what the loss needs of the rollout and the update (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the step's statistics (:data:`STEP_STATS`), and whether the step was applied
            (False: the update should stop)
        """
        self.needs_warm_up = False
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
        # The C++ wrapper runs the graph's kernels without a Python function around them.
        self.compiled = th.compile(self.step, options={"cpp_wrapper": True})
        #: whether the next call compiles the step (see :meth:`warm_up`)
        self.needs_warm_up = True
        # Computed at an update's first step: the update as the compiled step takes it (its
        # scheduled numbers as tensors), and the Adam scalars of its coming steps (within an
        # update only these steps advance the counters; lr and the optimizer's state change between updates).
        self._update: UpdateInputs | None = None
        self._compiled_update: UpdateInputs | None = None
        self._adam_rows: tuple[th.Tensor, th.Tensor] = (th.empty(0), th.empty(0))
        self._row = ADAM_ROWS

    def warm_up(self, update: UpdateInputs, idx: th.Tensor) -> None:
        """Compile the step now, by applying it to copies of the parameters and of the optimizer's state.

        Leaves parameters and optimizer state as they are; the next call reuses the compiled step.

        :param update: inputs of the shapes and settings of the coming update (any values)
        :param idx: indices of a minibatch
        """
        originals = self.optimizer.param_groups[0]["params"]
        without_state = [param for param in originals if not self.optimizer.state.get(param)]
        state = tuple([tensor.clone() for tensor in tensors] for tensors in adam_state(self.optimizer))
        for param in without_state:  # as before: the first real step creates it
            del self.optimizer.state[param]
        params = [th.nn.Parameter(param.detach().clone()) for param in originals]
        self._apply(params, state, update, idx)  # type: ignore[arg-type]
        self.needs_warm_up = False

    def __call__(self, update: UpdateInputs, idx: th.Tensor) -> tuple[th.Tensor, bool]:
        """One step on the minibatch ``idx``, always applied.

        :param update: what the loss needs of the rollout and the update (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the step's statistics (:data:`STEP_STATS`), and True
        """
        self.needs_warm_up = False
        return self._apply(self.optimizer.param_groups[0]["params"], adam_state(self.optimizer), update, idx), True

    def _apply(
        self,
        params: list[th.Tensor],
        state: tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor]],
        update: UpdateInputs,
        idx: th.Tensor,
    ) -> th.Tensor:
        """Run the compiled step on these parameters and Adam state (updated in place); return its statistics.

        :param params: the optimizer's parameters, in its order (or copies of them, :meth:`warm_up`)
        :param state: their ``step``, ``exp_avg`` and ``exp_avg_sq`` (:func:`adam_state`, or copies)
        :param update: what the loss needs of the rollout and the update (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the statistics named in :data:`STEP_STATS`
        """
        group = self.optimizer.param_groups[0]
        if update is not self._update:
            # Scheduled numbers as tensors: a float would be compiled in, and each new value recompile the step.
            settings = {
                name: th.tensor(getattr(update, name), dtype=th.float64, device=params[0].device)
                for name in ("clip_pi", "clip_mu", "zeta")
            }
            self._update, self._compiled_update, self._row = update, update._replace(**settings), ADAM_ROWS
        if self._row == ADAM_ROWS:
            # The step counters advance by one per step: the scalars of the coming steps at once.
            self._adam_rows = adam_scalars(state[0], group["lr"], group["betas"], ADAM_ROWS)
            self._row = 0
        step_sizes, bias_correction2_sqrts = (rows[self._row] for rows in self._adam_rows)
        self._row += 1
        adam_tensors = (params, *state, step_sizes, bias_correction2_sqrts)
        return self.compiled(adam_tensors, self.names, self._compiled_update, idx)

    def step(
        self,
        adam_tensors: tuple[list[th.Tensor], list[th.Tensor], list[th.Tensor], list[th.Tensor], th.Tensor, th.Tensor],
        names: list[str],
        update: UpdateInputs,
        idx: th.Tensor,
    ) -> th.Tensor:
        """The function that is compiled: loss, gradients, clipping and the Adam update.

        :param adam_tensors: the optimizer's parameters, their ``step``, ``exp_avg`` and
            ``exp_avg_sq``, and their step sizes and square roots of the second bias correction
            (:func:`adam_scalars`)
        :param names: the names of the parameters in the loss module
        :param update: what the loss needs (:class:`UpdateInputs`)
        :param idx: indices of the minibatch's samples
        :return: the statistics named in :data:`STEP_STATS`
        """
        params, steps, exp_avgs, exp_avg_sqs, step_sizes, bias_correction2_sqrts = adam_tensors

        def loss_of(values: tuple[th.Tensor, ...]) -> tuple[th.Tensor, th.Tensor]:
            return th.func.functional_call(self.loss, dict(zip(names, values, strict=True)), (update, idx))

        grads, (_, step_stats) = th.func.grad_and_value(loss_of, has_aux=True)(tuple(params))
        if self.max_grad_norm is not None:
            grads = clip_by_total_norm(grads, self.max_grad_norm)
        group = self.optimizer.param_groups[0]
        adam_update_(
            params,
            grads,
            (steps, exp_avgs, exp_avg_sqs),
            step_sizes,
            bias_correction2_sqrts,
            group["betas"],
            group["eps"],
        )
        return step_stats


# ------------------------------------------------------------------ the choice
#: With ``torch_compile="auto"``: the shortest ``learn`` that compiles (compiling takes tens of
#: seconds, minutes with a cold compile cache).
COMPILE_FROM_TIMESTEPS = 200_000


def has_cxx_compiler() -> bool:
    """Whether ``torch.compile`` finds a C++ compiler for CPU code.

    :return: True if a compiler is found
    """
    from torch._inductor import cpp_builder, exc

    try:
        cpp_builder.get_cpp_compiler()
    except exc.InvalidCxxCompiler:
        return False
    return True


def check_cxx_compiler() -> None:
    """``torch.compile`` builds C++ code for the CPU: fail at once, and clearly, without a compiler.

    :raises RuntimeError: if no C++ compiler is found
    """
    if not has_cxx_compiler():
        raise RuntimeError(
            "torch_compile=True needs a C++ compiler on the CPU (g++ or clang++ on PATH, or the CXX "
            "environment variable); install one or use torch_compile=False."
        )


def compiles(torch_compile: bool | str, device: th.device, total_timesteps: int | None = None) -> bool:
    """Whether to compile, from MAPPOC's ``torch_compile`` setting.

    :param torch_compile: True, False or ``"auto"`` (compile on the CPU, with a C++ compiler, for a ``learn`` of at
        least :data:`COMPILE_FROM_TIMESTEPS` steps)
    :param device: where the networks run
    :param total_timesteps: the steps of the coming ``learn`` (None: before any ``learn``, when ``"auto"`` does not
        compile)
    :return: whether to compile the sampling and the gradient step
    :raises RuntimeError: for ``torch_compile=True`` on the CPU without a C++ compiler
    """
    if torch_compile == "auto":
        long_enough = total_timesteps is not None and total_timesteps >= COMPILE_FROM_TIMESTEPS
        return device.type == "cpu" and long_enough and has_cxx_compiler()
    if torch_compile and device.type == "cpu":
        check_cxx_compiler()
    return bool(torch_compile)


def make_gradient_step(
    loss: MAPPOCLoss,
    optimizer: th.optim.Optimizer,
    max_grad_norm: float | None,
    target_kl: float | None,
    compiled: bool,
) -> GradientStep | FusedGradientStep:
    """The gradient step for these settings: fused and compiled where it can be, else the usual one.

    Early stopping (``target_kl``) looks at a step's statistics before applying it: only the unfused step can.

    :param loss: the loss module
    :param optimizer: the optimizer of the loss's policy
    :param max_grad_norm: largest joint gradient norm (None: no clipping)
    :param target_kl: see :class:`GradientStep` (None: never stop early)
    :param compiled: whether to compile
    :return: a :class:`FusedGradientStep` if compiled with plain Adam and no ``target_kl``, else a
        :class:`GradientStep` (with a compiled loss if compiled)
    """
    if compiled and fusable_adam(optimizer) and target_kl is None:
        return FusedGradientStep(loss, optimizer, max_grad_norm)
    return GradientStep(loss, optimizer, max_grad_norm, target_kl, compile_loss=compiled)
