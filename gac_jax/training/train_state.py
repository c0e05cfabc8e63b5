"""Train state, optimizer and the non-finite guard shared by the detection and depth trainers."""

from __future__ import annotations

from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax


@flax.struct.dataclass
class TrainState:
    """Everything a step needs and a checkpoint stores.

    ``nonfinite`` latches to True when a step produced a NaN/inf loss or
    gradient; such a step leaves params, batch stats and optimizer state
    unchanged, so the state stays the last good one.
    """

    step: jax.Array
    params: Any
    batch_stats: Any
    opt_state: Any
    rng: jax.Array  # raw uint32 key data (checkpointable), see jax.random.key_data
    nonfinite: jax.Array

    @classmethod
    def create(cls, params, batch_stats, tx: optax.GradientTransformation, seed: int) -> TrainState:
        return cls(
            step=jnp.zeros((), jnp.int32),
            params=params,
            batch_stats=batch_stats,
            opt_state=tx.init(params),
            rng=jax.random.key_data(jax.random.key(seed)),
            nonfinite=jnp.zeros((), bool),
        )

    def step_key(self, name: str = "dropout") -> jax.Array:
        """A typed PRNG key for this step (deterministic in (seed, step, name))."""
        key = jax.random.wrap_key_data(self.rng)
        key = jax.random.fold_in(key, self.step)
        return jax.random.fold_in(key, sum(map(ord, name)))


def learning_rate_schedule(
    base_lr: float,
    final_lr: float,
    total_steps: int,
    steps_per_epoch: int | None = None,
    warmup_steps: int = 0,
) -> optax.Schedule:
    """Cosine decay from ``base_lr`` to ``final_lr``.

    With ``steps_per_epoch`` the rate is constant within an epoch and follows
    the cosine over epochs (the reference's per-epoch CosineAnnealingLR);
    otherwise it decays per step. Optional linear warm-up.
    """
    if steps_per_epoch:
        num_epochs = max(total_steps // steps_per_epoch, 1)

        def schedule(step):
            epoch = jnp.minimum(step // steps_per_epoch, num_epochs - 1)
            cos = 0.5 * (1 + jnp.cos(jnp.pi * epoch / num_epochs))
            return final_lr + (base_lr - final_lr) * cos
    else:

        def schedule(step):
            t = jnp.clip(step / max(total_steps, 1), 0.0, 1.0)
            return final_lr + (base_lr - final_lr) * 0.5 * (1 + jnp.cos(jnp.pi * t))

    if warmup_steps:
        warm = optax.linear_schedule(0.0, base_lr, warmup_steps)
        return optax.join_schedules([warm, lambda s: schedule(s + warmup_steps)], [warmup_steps])
    return schedule


def make_optimizer(
    schedule: optax.Schedule, clip_norm: float | None, weight_decay: float = 0.0
) -> optax.GradientTransformation:
    """Adam(W) with global-norm gradient clipping (reference: clip 0.1, Adam, no weight decay)."""
    parts = []
    if clip_norm:
        parts.append(optax.clip_by_global_norm(clip_norm))
    if weight_decay:
        parts.append(optax.adamw(schedule, weight_decay=weight_decay))
    else:
        parts.append(optax.adam(schedule))
    return optax.chain(*parts)


def apply_gradients_guarded(
    state: TrainState,
    tx: optax.GradientTransformation,
    grads,
    new_batch_stats,
    loss: jax.Array,
) -> tuple[TrainState, jax.Array]:
    """Applies an update unless the loss or gradients are non-finite; returns (state, grad_norm)."""
    grad_norm = optax.tree.norm(grads)
    finite = jnp.isfinite(loss) & jnp.isfinite(grad_norm)
    updates, new_opt_state = tx.update(grads, state.opt_state, state.params)
    new_params = optax.apply_updates(state.params, updates)

    def keep(new, old):
        return jax.tree.map(lambda n, o: jnp.where(finite, n, o), new, old)

    return (
        state.replace(
            step=state.step + 1,
            params=keep(new_params, state.params),
            batch_stats=keep(new_batch_stats, state.batch_stats),
            opt_state=keep(new_opt_state, state.opt_state),
            nonfinite=state.nonfinite | ~finite,
        ),
        grad_norm,
    )
