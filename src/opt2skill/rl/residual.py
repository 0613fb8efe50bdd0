"""A residual policy on a frozen actor, as one wider MLP (`DistillConfig.finetune = "residual"`).

PPO after distillation forgets the distilled skill: a 1 % change of the distilled weights in PPO's
direction ruins flat-ground tracking (docs/distill.md). A residual policy keeps the distilled actor
intact and lets PPO learn only a correction added to its action.

Here the residual is not a second network but extra units of the same MLP, so that everything
downstream of an actor (checkpoints, `rl.policy`, ONNX export, the 2 kHz player) is unchanged:

- every hidden layer has the base actor's units first, then `residual_dims` new ones;
- the base units read only the input and base units, with the base's weights, and never change
  (their gradients are zeroed by hooks, so Adam never moves them);
- the residual units read the input and every unit of the layer below (base features included) and
  are trained;
- the output layer adds the base units' contribution (frozen, the base's weights and bias) and the
  residual units' (trained, starting at zero).

At the start the widened actor's action equals the base actor's exactly; the observation
normalizer is the base's and stays fixed (the base's weights are only valid on its statistics).
"""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel


def linear_layers(actor: MLPModel) -> list[torch.nn.Linear]:
    return [m for m in actor.mlp if isinstance(m, torch.nn.Linear)]


def hidden_dims(actor_state: dict[str, torch.Tensor]) -> tuple[int, ...]:
    """The hidden widths of an actor from its state dict (every `mlp.K.weight` but the last)."""
    weights = sorted((int(k.split(".")[1]), v) for k, v in actor_state.items()
                     if k.startswith("mlp.") and k.endswith(".weight"))
    return tuple(int(w.shape[0]) for _, w in weights[:-1])


def widened(base: tuple[int, ...], residual: tuple[int, ...]) -> tuple[int, ...]:
    if len(base) != len(residual):
        raise ValueError(f"residual widths {residual} need one per base hidden layer {base}")
    return tuple(b + r for b, r in zip(base, residual))


def load_base(actor: MLPModel, base_state: dict[str, torch.Tensor]) -> None:
    """Put the base actor `base_state` into the widened `actor`: base blocks copied, base units cut off
    from residual units, the residual's output weights zeroed (so the action is the base's), the
    observation normalizer and action std taken from the base."""
    layers = linear_layers(actor)
    keys = [k for _, k in sorted((int(k.split(".")[1]), k) for k in base_state
                                 if k.startswith("mlp.") and k.endswith(".weight"))]
    if len(keys) != len(layers):
        raise ValueError(f"the base actor has {len(keys)} layers, the widened one {len(layers)}")
    last = len(layers) - 1
    with torch.no_grad():
        for i, (layer, key) in enumerate(zip(layers, keys)):
            w, b = base_state[key], base_state[key[: -len("weight")] + "bias"]
            rows, cols = w.shape
            if rows > layer.weight.shape[0] or cols > layer.weight.shape[1] or (i == last and rows != layer.weight.shape[0]):
                raise ValueError(f"layer {i}: the base's {tuple(w.shape)} does not fit in {tuple(layer.weight.shape)}")
            layer.weight[:rows, :cols] = w
            layer.weight[:rows, cols:] = 0.0  # base units never read residual units; the residual output starts at 0
            layer.bias[:rows] = b
        state = actor.state_dict()
        for key, value in base_state.items():
            if not key.startswith("mlp."):
                state[key].copy_(value)


def freeze_base(actor: MLPModel, base_dims: tuple[int, ...]) -> list:
    """Zero the gradients of the base units (and of the output layer's base columns and bias) from now
    on, and stop the observation normalizer from following the data. Returns the hook handles."""
    layers = linear_layers(actor)
    if len(base_dims) != len(layers) - 1:
        raise ValueError(f"base widths {base_dims} do not match an actor with {len(layers) - 1} hidden layers")
    handles = []
    for i, layer in enumerate(layers):
        weight_mask = torch.ones_like(layer.weight)
        bias_mask = torch.ones_like(layer.bias)
        if i < len(layers) - 1:
            weight_mask[: base_dims[i]] = 0.0
            bias_mask[: base_dims[i]] = 0.0
        else:
            weight_mask[:, : base_dims[i - 1]] = 0.0
            bias_mask[:] = 0.0
        handles.append(layer.weight.register_hook(lambda g, m=weight_mask: g * m))
        handles.append(layer.bias.register_hook(lambda g, m=bias_mask: g * m))
    actor.obs_normalization = False  # rsl_rl's update_normalization is a no-op from now on
    return handles
