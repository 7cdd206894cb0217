"""The actor-critic loss base of DDPG, TD3, D4PG and SAC; each sibling overrides only where its paper differs.

Shaped like TorchRL's ``TD3Loss`` (``_AcceptedKeys``, ``actor_loss``/``value_loss``, targets as
``target_*_params`` so TorchRL's ``SoftUpdate`` drives them), but built for speed on CPU:

* a critic ensemble (TD3's and SAC's twins) is ONE :class:`~torcsrl.nets.Critic` with stacked weights
  (one batched matmul per layer) instead of ``vmap`` over parameter sets;
* the actor loss runs the critic with detached weights (:meth:`~torcsrl.nets.Critic.member`, ``detached``), so
  no critic weight gradient is computed there;
* the target networks are module copies bound to the target parameter tensors
  (:func:`~torcsrl.objectives.common.bind_target`), not parameters swapped in on every call;
* the networks are called on plain tensors, so no TensorDict is built per forward;
* the public ``actor_loss`` / ``value_loss`` are the fast path the training update calls: TorchRL's metaclass
  wraps every public ``*_loss`` in exploration and recurrent-mode contexts (~20 us a call), which networks called
  on plain tensors never read, so :class:`DirectLossMeta` leaves them as written (``forward`` stays wrapped).

What the base holds: the keys, the functional parameters and targets, the batch unpacking (DrQ shifts, asymmetric
critic inputs), priority weights, the bootstrap ``r + gamma^n Q'`` with termination masked (truncation bootstraps),
the deterministic actor loss ``-Q1(s, mu(s))``, the regression value loss to :meth:`ActorCriticLoss.target`, and
``forward``. What a sibling overrides: :meth:`~ActorCriticLoss.target` (DDPG, TD3, SAC), the value loss (D4PG's
cross-entropy), the value of a critic output (D4PG's expectation over atoms), and, for SAC's stochastic actor, the
actor loss (with its temperature loss).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import dispatch
from tensordict.utils import NestedKey
from torch import nn
from torchrl.objectives.common import LossModule, _LossMeta

from torcsrl.nets import Critic
from torcsrl.objectives.common import ObsUnpacker, bind_target, discount

_LOSSES = {
    "l2": lambda x, y: (x - y).pow(2),
    "smooth_l1": lambda x, y: nn.functional.smooth_l1_loss(x, y, reduction="none"),
    "l1": lambda x, y: (x - y).abs(),
}


class DirectLossMeta(_LossMeta):
    """TorchRL's ``_LossMeta`` without its wrapper around the public ``*_loss`` methods of a class (see module docstring)."""

    def __init__(cls, name, bases, attr_dict):
        super().__init__(name, bases, attr_dict)
        for key, value in attr_dict.items():
            if not key.startswith("_") and key.endswith("loss") and callable(value):
                setattr(cls, key, value)


class ActorCriticLoss(LossModule, metaclass=DirectLossMeta):
    """Deterministic actor-critic loss: actor ``-Q1(s, mu(s))``, critics regressed on :meth:`target` (abstract).

    Args:
        actor_network: the actor (``forward(*obs) -> action``).
        qvalue_network: the critic ensemble (``forward(*obs, action) -> [E, B, out_dim]``).

    Keyword Args:
        obs_keys: observation keys, in the order the networks take them.
        image_keys: the subset of ``obs_keys`` that are images (DrQ-augmented when ``augment_shift > 0``).
        action_low, action_high: action bounds (target actions are clipped into them).
        gamma: discount per env step [-].
        loss_function: critic regression ``"l2"`` | ``"smooth_l1"`` | ``"l1"``.
        augment_shift: DrQ random-shift pad [pixels] applied to image observations (0 = off).
        critic_obs_keys, critic_image_keys: what the critics see when it differs from the actor's input (asymmetric
            actor-critic, Pinto et al. 2017: privileged state for the critics, the camera for the actor); ``None`` =
            ``obs_keys`` (one unpacking per batch, shared).
        use_prioritized_weights: weight the losses by ``priority_weight`` when present ("auto").
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys (``set_keys``).

        Attributes:
            action: the action taken.  reward / done / terminated: read under ``"next"``.
            priority: where the per-sample TD error is written for prioritized replay.
            priority_weight: importance-sampling weights from a prioritized buffer.
            steps_to_next_obs: n of n-step batches (the discount is ``gamma**n``), as TorchRL's ``MultiStepTransform`` writes it.
        """

        action: NestedKey = "action"
        state_action_value: NestedKey = "state_action_value"
        priority: NestedKey = "td_error"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        priority_weight: NestedKey = "priority_weight"
        steps_to_next_obs: NestedKey = "steps_to_next_obs"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_actor", "loss_qvalue", "pred_value", "target_value"]
    #: the actor has a target copy (DDPG, TD3, D4PG); SAC's targets act with the online policy
    delay_actor = True

    actor_network: nn.Module
    qvalue_network: nn.Module
    actor_network_params: TensorDictParams
    qvalue_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: nn.Module,
        qvalue_network: Critic,
        *,
        obs_keys: list[str],
        image_keys: list[str] = (),
        action_low: torch.Tensor,
        action_high: torch.Tensor,
        gamma: float = 0.99,
        loss_function: str = "l2",
        augment_shift: int = 0,
        critic_obs_keys: list[str] | None = None,
        critic_image_keys: list[str] = (),
        use_prioritized_weights: str | bool = "auto",
    ) -> None:
        super().__init__()
        if loss_function not in _LOSSES:
            raise ValueError(f"unknown loss_function {loss_function!r}; known: {', '.join(_LOSSES)}")
        self.use_prioritized_weights = use_prioritized_weights
        self.convert_to_functional(actor_network, "actor_network", create_target_params=self.delay_actor)
        self.convert_to_functional(qvalue_network, "qvalue_network", create_target_params=True)
        if self.delay_actor:
            self.__dict__["target_actor"] = bind_target(actor_network, self._modules["target_actor_network_params"])
        self.__dict__["target_qvalue"] = bind_target(qvalue_network, self._modules["target_qvalue_network_params"])
        self.num_qvalue_nets = qvalue_network.num_nets
        self.gamma = float(gamma)
        self.loss_function = loss_function
        self._dist = _LOSSES[loss_function]
        self.register_buffer("min_action", torch.as_tensor(action_low, dtype=torch.float32).clone())
        self.register_buffer("max_action", torch.as_tensor(action_high, dtype=torch.float32).clone())
        self.obs = ObsUnpacker(obs_keys, list(image_keys), augment_shift)
        self.critic_obs = None if critic_obs_keys is None else ObsUnpacker(critic_obs_keys, list(critic_image_keys), augment_shift)

    # TorchRL bookkeeping -------------------------------------------------------------
    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        keys = [
            self.tensor_keys.action,
            ("next", self.tensor_keys.reward),
            ("next", self.tensor_keys.done),
            ("next", self.tensor_keys.terminated),
            *self.obs.keys,
            *[("next", k) for k in self.obs.keys],
        ]
        if self.critic_obs is not None:
            keys += [*self.critic_obs.keys, *[("next", k) for k in self.critic_obs.keys]]
        return keys

    def _weights(self, td: TensorDictBase) -> torch.Tensor | None:
        w = self._maybe_get_priority_weight(td)
        return None if w is None else w.reshape(-1)

    @staticmethod
    def _reduce(x: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
        return x.mean() if w is None else (x * w).mean()

    # shared pieces --------------------------------------------------------------------
    def critic_inputs(self, td: TensorDictBase, obs: list[torch.Tensor] | None = None, nxt: bool = False) -> list[torch.Tensor]:
        """What the critics see: the actor's observations ``obs`` (unpacked here when None), or their own keys."""
        if self.critic_obs is not None:
            return self.critic_obs(td, nxt=nxt)
        return self.obs(td, nxt=nxt) if obs is None else obs

    def critic_value(self, out: torch.Tensor) -> torch.Tensor:
        """A critic output ``[..., out_dim]`` as a value ``[...]``: the scalar Q (D4PG: the expectation over its atoms)."""
        return out.squeeze(-1)

    def reward_discount(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | float]:
        """(reward [B], terminated [B], gamma^n [B] or a float) of a batch."""
        nxt = td.get("next")
        g = discount(td, self.gamma, self.tensor_keys.steps_to_next_obs)
        return (nxt.get(self.tensor_keys.reward).reshape(-1), nxt.get(self.tensor_keys.terminated).reshape(-1),
                g.reshape(-1) if torch.is_tensor(g) else g)

    def bootstrap(self, td: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
        """``y = r + gamma^n V'(s')``, ``y = r`` where the episode terminated (a time limit bootstraps)."""
        reward, term, g = self.reward_discount(td)
        return torch.where(term, reward, reward + g * next_value)

    def target(self, td: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """(regression target y [B], next-state value [B]) of a batch, without gradients: the sibling's own."""
        raise NotImplementedError

    # the two losses -------------------------------------------------------------------
    def actor_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict]:
        """``-Q1(s, mu(s))`` with the critic's weights detached: gradients reach the actor only.

        The metadata's ``"_action"`` (mu(s), with its graph) and ``"_q"`` are for the actor's optional terms
        (:func:`torcsrl.agents._build.actor_regularisers`); the training update pops them, ``forward`` drops them."""
        obs = self.obs(tensordict)
        action = self.actor_network(*obs)
        q = self.critic_value(self.qvalue_network.member(*self.critic_inputs(tensordict, obs), action, index=0))
        loss = self._reduce(-q, self._weights(tensordict))
        return loss, {"state_action_value_actor": q.detach().mean(), "_action": action, "_q": q.detach()}

    def value_loss(self, tensordict: TensorDictBase, td_error: bool = False) -> tuple[torch.Tensor, dict]:
        """Sum over critics of the mean regression loss to :meth:`target`; ``td_error``: also the per-sample
        ``max_i |Q_i - y|`` (the priority of prioritized replay)."""
        target, next_q = self.target(tensordict)
        q = self.critic_value(self.qvalue_network(*self.critic_inputs(tensordict), tensordict.get(self.tensor_keys.action)))  # [E, B]
        w = self._weights(tensordict)
        if w is None and self.loss_function == "l2":  # one fused kernel: sum_e mean_b (q - y)^2
            loss = nn.functional.mse_loss(q, target.expand_as(q)) * q.shape[0]
        else:
            loss = self._reduce(self._dist(q, target.expand_as(q)).sum(0), w)
        meta = {"pred_value": q.detach().mean(), "next_state_value": next_q.mean(), "target_value": target.mean()}
        if td_error:
            with torch.no_grad():
                meta["td_error"] = torch.amax((q - target).abs_(), 0)
        return loss, meta

    @dispatch
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Both losses and their metrics in one TensorDict (TorchRL's interface; the training update calls the two
        losses itself); the per-sample TD error is written into ``tensordict`` under ``priority``."""
        loss_qvalue, meta_v = self.value_loss(tensordict, td_error=True)
        loss_actor, meta_a = self.actor_loss(tensordict)
        tensordict.set(self.tensor_keys.priority, meta_v.pop("td_error").unsqueeze(-1))
        return TensorDict(loss_actor=loss_actor, loss_qvalue=loss_qvalue, **self._more_losses(meta_a),
                          **{k: v for k, v in {**meta_a, **meta_v}.items() if not k.startswith("_")})

    def _more_losses(self, meta_actor: dict) -> dict[str, torch.Tensor]:
        """Losses beside the actor's and the critics' in ``forward`` (SAC: the temperature's)."""
        return {}
