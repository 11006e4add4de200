"""The whole pi0.5 policy: prefix KV cache, action expert, flow-matching Euler sampler, with steering.

`Pi05Policy.sample_actions` computes what openpi's `PI0Pytorch.sample_actions` computes (spec 10.4): one
prefix forward fills a per-layer KV cache, then `num_steps` Euler steps from noise at t = 1 run the action
tokens through the expert. The prefix keeps `Pi05Prefix`'s exact savings (a camera masked for the whole
batch is skipped, language padding after the longest prompt is trimmed): those columns are invalid, and
invalid prefix keys are masked for every action token too.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import torch
from torch import nn

from steering_core.devices import resolve_device, resolve_dtype
from steering_core.pi05.arch import ExpertArch, Pi05Arch
from steering_core.pi05.checkpoint import (
    check_expert_tensors,
    expert_arch_from_checkpoint,
    read_expert_tensors,
)
from steering_core.pi05.denoise import Denoiser
from steering_core.pi05.expert import ActionExpert, euler_times, expert_checkpoint_key
from steering_core.pi05.layouts import LayoutName, resolve_checkpoint
from steering_core.pi05.model import MASKED_LOGIT, Attention, KeyValueRecorder, Pi05Prefix, parameter_dtype
from steering_core.pi05.norm_stats import LIBERO_ASSET_ID
from steering_core.pi05.normalization import ROBOT_ACTION_DIM
from steering_core.pi05.observation import (
    IMAGE_KEY,
    PROMPT_KEY,
    STATE_KEY,
    WRIST_IMAGE_KEY,
    ObservationBatch,
    observation_batch,
)
from steering_core.pi05.preprocess import Cameras
from steering_core.pi05.robot_side import Normalization, robot_side
from steering_core.pi05.steering import (
    Clamp,
    Splice,
    Steering,
    SteeringArg,
    apply_clamp,
    as_list,
    check_steerings,
    expert_additions,
    expert_clamps,
    lm_additions,
    lm_clamps,
    stack_clamps,
    stack_entries,
)
from steering_core.pi05.tokenizer import PromptFormat, PromptTokenizer, TokenizedPrompt

logger = logging.getLogger(__name__)

LIBERO_STATE_DIM = 8  # eef position 3, axis-angle 3, gripper qpos 2: the warm-up's dummy state
DEFAULT_STEPS = 10  # sample_actions' default number of Euler steps



class Pi05Policy(nn.Module):
    """pi0.5 (prefix + action expert + sampler) with residual-stream steering; build with `from_checkpoint`."""

    def __init__(
        self,
        prefix: Pi05Prefix,
        expert: ActionExpert,
        action_horizon: int,
        tokenizer: PromptTokenizer | None,
        normalization: Normalization,
        compiled: bool = False,
        cameras: Cameras = Cameras(),
    ):
        super().__init__()
        self.prefix = prefix
        self.expert = expert
        self.action_horizon = action_horizon
        self.tokenizer = tokenizer
        self.normalization = normalization
        self.cameras = cameras
        self.attention: Attention = "sdpa"  # the prefix's fused attention; "eager" is openpi's explicit mask
        self.denoiser = Denoiser(expert, compiled)

    @property
    def compiled(self) -> bool:
        """Return whether the denoising step runs compiled (`steering_core.pi05.denoise`)."""
        return self.denoiser.compiled

    @classmethod
    def from_checkpoint(
        cls,
        path: str | os.PathLike,
        arch: Pi05Arch | None = None,
        device: str | torch.device | None = None,
        dtype: str | torch.dtype | None = None,
        action_horizon: int | None = None,
        tokenizer_path: str | os.PathLike | None = None,
        prompt_format: PromptFormat | None = None,
        norm_stats_path: str | os.PathLike | None = None,
        asset_id: str = LIBERO_ASSET_ID,
        expert_arch: ExpertArch | None = None,
        compiled: bool | None = None,
        layout: LayoutName | str = LayoutName.AUTO,
        max_token_len: int | None = None,
    ) -> Pi05Policy:
        """Return the policy of a pi0.5 checkpoint: openpi's converted PyTorch folder or lerobot's PI05Policy folder
        (detected, or `layout` forced), or the model.safetensors of either.

        Args:
            arch: language model and SigLIP dimensions; default the real pi0.5.
            device, dtype: default CUDA with the layout's bfloat16 policy (its float32 parameters) when available,
                else CPU float32.
            action_horizon: actions per chunk; default the checkpoint's (openpi `action_horizon`, lerobot
                `chunk_size`), else 10 (pi05_libero).
            tokenizer_path: PaliGemma's SentencePiece model or tokenizer.json; needed by `infer`, `tokenize` and
                `instruction_mask` only.
            prompt_format: how the checkpoint reads its prompt; default libero for openpi (pi05_libero: no state),
                discrete_state for lerobot (its preprocessor always puts the state in the prompt).
            norm_stats_path, asset_id: openpi only: the norm stats for `robot_actions` (and the discrete-state
                prompt); default `<checkpoint>/assets/<asset_id>/norm_stats.json`, read on first use. lerobot's
                statistics come from its processor files.
            expert_arch: expert dimensions; default gemma_300m beside the real language model, else read
                from the checkpoint's shapes.
            compiled: run the denoising step compiled (`steering_core.pi05.denoise`: the same actions within
                rounding, a one-off compilation per batch size, paid by `warm_up`); default on CUDA only.
            max_token_len: the tokenizer's prompt length; default lerobot's tokenizer_max_length, else 200.
        """
        arch = arch or Pi05Arch()
        checkpoint = resolve_checkpoint(path, layout)
        robot = robot_side(checkpoint, arch, prompt_format, norm_stats_path, asset_id, action_horizon, max_token_len)
        expert_arch = expert_arch or expert_arch_from_checkpoint(checkpoint, arch)
        expert_arch.check_pairs_with(arch)
        # the expert's names and shapes fail a prefix-only or mismatched file before any data is read
        check_expert_tensors(checkpoint, expert_arch)
        tokenizer = None
        if tokenizer_path is not None:
            tokenizer = PromptTokenizer(tokenizer_path, robot.max_token_len, robot.prompt_format)
            if tokenizer.vocab_size > arch.vocab_size:
                raise ValueError(
                    f"{tokenizer_path}: {tokenizer.vocab_size} pieces, more than the model's vocab_size "
                    f"{arch.vocab_size}; pass the tokenizer the checkpoint was trained with"
                )
        device = resolve_device(device)
        dtype = resolve_dtype(dtype, device)
        prefix = Pi05Prefix.from_checkpoint(checkpoint, arch, device=device, dtype=dtype)
        with torch.device("meta"):
            expert = ActionExpert(expert_arch)
        local = {expert_checkpoint_key(name): name for name, _ in expert.named_parameters()}
        tensors = read_expert_tensors(
            checkpoint,
            expert_arch,
            lambda key: (device, parameter_dtype(key, dtype, checkpoint.layout)),
        )
        expert.load_state_dict({local[key]: tensor for key, tensor in tensors.items()}, strict=True, assign=True)
        expert.requires_grad_(False).eval()
        compiled = device.type == "cuda" if compiled is None else compiled
        policy = cls(prefix, expert, robot.action_horizon, tokenizer, robot.normalization, compiled, robot.cameras)
        policy.eval()
        logger.info("pi0.5 policy from %s on %s in %s (expert %s%s)", checkpoint.describe, device, dtype, expert_arch,
                    ", compiled denoising" if compiled else "")
        return policy

    # ------------------------------------------------------------------ properties

    @property
    def arch(self) -> Pi05Arch:
        return self.prefix.arch

    @property
    def expert_arch(self) -> ExpertArch:
        return self.expert.expert_arch

    @property
    def device(self) -> torch.device:
        return self.prefix.device

    @property
    def action_dim(self) -> int:
        """Return the model's action width (32: LIBERO's 7 padded)."""
        return self.expert_arch.action_dim

    @property
    def state_dim(self) -> int:
        """Return the widest state this policy takes: the width its normaliser's state statistics describe, else
        the action width (openpi pads the state to it; a wider one it cannot normalise or pad)."""
        return self.normalization.state_dim or self.action_dim

    @property
    def metadata(self) -> dict[str, Any]:
        """Return a JSON-ready summary of the policy (served to clients)."""
        return {
            "model": "pi05",
            "action_horizon": self.action_horizon,
            "action_dim": self.action_dim,
            "state_dim": self.state_dim,
            "robot_action_dim": ROBOT_ACTION_DIM,
            "image_size": self.arch.image_size,
            "max_token_len": self.tokenizer.max_len if self.tokenizer else None,
            "prompt_format": self.tokenizer.prompt_format.value if self.tokenizer else None,
            "checkpoint": str(self.prefix.model_file),
            "layout": self.layout,
            "norm_stats": str(self.normalization.source),
            "device": str(self.device),
            "dtype": str(self.prefix.compute_dtype).removeprefix("torch."),
            "lm": self.arch.model_dump(),
            "expert": self.expert_arch.model_dump(),
            "steerable": {
                "lm": {"width": self.arch.width, "layers": self.arch.depth},
                "expert": {"width": self.expert_arch.width, "layers": self.expert_arch.depth},
            },
        }

    # ------------------------------------------------------------------ sampling

    def sample_actions(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
        noise: torch.Tensor | None = None,
        num_steps: int = DEFAULT_STEPS,
        steering: SteeringArg = None,
        generator: torch.Generator | None = None,
        splice: Splice | None = None,
    ) -> torch.Tensor:
        """Return model actions (B, action_horizon, action_dim) float32, as openpi's `sample_actions`.

        images / image_masks: per camera slot (B, 3, S, S) float in [-1, 1] and (B,) bool, in openpi's
        order (`libero_camera_slots`); tokens (B, T) int64, token_mask (B, T) bool. noise: (B, H, A) float32,
        default N(0, 1) from `generator`. steering: one Steering, a list applied together, or None; each adds
        (mode "add") or clamps its projection to a level (mode "clamp"; at one layer clamps first, then additions,
        at most one clamp a layer). splice: a language-model layer's residuals at chosen prompt positions replaced
        (before its steering).
        """
        entries = [as_list(steering)]
        return self._sample(images, image_masks, tokens, token_mask, entries, noise, num_steps, generator, splice)[0]

    def sample_actions_sweep(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
        steerings: Sequence[SteeringArg],
        noise: torch.Tensor | None = None,
        num_steps: int = DEFAULT_STEPS,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Return (len(steerings), B, action_horizon, action_dim): `sample_actions` once per entry, same noise.

        The prefix up to the shallowest steered language-model layer is computed once; the deeper layers
        and the denoising loop run every entry in one batch.
        """
        if isinstance(steerings, Steering) or not len(steerings):
            raise ValueError("steerings must be a non-empty list of entries (each a Steering, a list, or None)")
        entries = [as_list(entry) for entry in steerings]
        return self._sample(images, image_masks, tokens, token_mask, entries, noise, num_steps, generator)

    @torch.no_grad()
    def _sample(
        self,
        images: Sequence[torch.Tensor],
        image_masks: Sequence[torch.Tensor],
        tokens: torch.Tensor,
        token_mask: torch.Tensor,
        entries: list[list[Steering]],
        noise: torch.Tensor | None,
        num_steps: int,
        generator: torch.Generator | None,
        splice: Splice | None = None,
    ) -> torch.Tensor:
        """Return (len(entries), B, H, A) actions; each entry's steerings apply to its own copy of the batch,
        the splice (if any) to every copy."""
        self.prefix.check_inputs(images, image_masks, tokens, token_mask)
        batch, n_tokens = tokens.shape
        check_steerings(entries, self.arch, self.expert_arch, batch, n_tokens, len(images))
        if splice is not None:
            splice.check(self.arch, batch, n_tokens)
        dt, times = euler_times(num_steps, self.device, self.accumulated_time)
        noise = self._noise(noise, batch, generator)
        images, image_masks, tokens, token_mask = self.prefix.on_device(images, image_masks, tokens, token_mask)
        entries = [[item.to(self.device) for item in entry] for entry in entries]
        splice = None if splice is None else splice.to(self.device)
        n = len(entries)

        hidden, pad, columns = self.prefix.embed_prefix(images, image_masks, tokens, token_mask)
        image_columns = len(images) * self.arch.tokens_per_image
        dtype = self.prefix.compute_dtype
        lm = [lm_additions(entry, token_mask, columns, image_columns, dtype) for entry in entries]
        lm_clamped = [lm_clamps(entry, token_mask, columns, image_columns) for entry in entries]
        replace = {} if splice is None else {splice.layer: splice.layer_function(token_mask, columns, image_columns)}
        keys_values = self._prefix_cache(hidden, pad, lm, lm_clamped, batch, replace)

        # action tokens: positions continue after the valid prefix tokens; they see every valid prefix key
        # and each other (one bidirectional block, spec 10.4)
        horizon = self.action_horizon
        positions = (pad.sum(dim=1, keepdim=True) + torch.arange(horizon, device=self.device)).repeat(n, 1)
        rotary = self.prefix.rotary_emb(hidden.new_empty(0, dtype=self.expert.compute_dtype), positions)
        allowed = torch.cat([pad, pad.new_ones(batch, horizon)], dim=1).repeat(n, 1)
        mask = torch.where(allowed, 0.0, MASKED_LOGIT).to(torch.float32)[:, None, None, :]
        steer = stack_entries([expert_additions(entry, self.expert.compute_dtype) for entry in entries],
                              batch)
        clamps = stack_clamps([expert_clamps(entry) for entry in entries], batch)
        full = self.arch.prefix_length(len(images), n_tokens)
        actions = self.denoiser.run(noise.repeat(n, 1, 1), times, dt, rotary, keys_values, mask, steer, clamps,
                                    full)
        return actions.view(n, batch, horizon, self.action_dim)

    def _prefix_cache(
        self, hidden: torch.Tensor, pad: torch.Tensor, lm: list[dict[int, torch.Tensor]],
        lm_clamped: list[dict[int, Clamp]], batch: int,
        replace: Mapping[int, Callable[[torch.Tensor], torch.Tensor]] | None = None,
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Return each language-model layer's keys and values for the entries stacked along the batch.

        Layers up to the shallowest steered one (added to or clamped) run once for the batch: steering a
        layer's output leaves its own keys and values unchanged. The deeper layers run once over all entries
        together. `replace` (splices, shared by every entry) applies wherever its layer runs.
        """
        last = self.arch.depth - 1
        steered = [layer for entry in [*lm, *lm_clamped] for layer in entry]
        split = min(steered) if steered else last
        n = len(lm)
        shared = KeyValueRecorder()
        out = self.prefix.decode(hidden, pad, [split], self.attention, cache=shared, replace=replace)[split]
        keys_values = [tuple(t.repeat(n, 1, 1, 1) for t in shared.layers[i]) for i in range(split + 1)]
        if split < last:
            additions, clamps = stack_entries(lm, batch), stack_clamps(lm_clamped, batch)
            out = out.repeat(n, 1, 1)
            if split in clamps:
                out = apply_clamp(out, clamps.pop(split))
            out = out + additions.pop(split, 0)
            rest = KeyValueRecorder()
            self.prefix.decode(out, pad.repeat(n, 1), [last], self.attention, start=split + 1, cache=rest,
                               additions=additions, replace=replace, clamps=clamps)
            keys_values += [rest.layers[i] for i in range(split + 1, last + 1)]
        return keys_values

    def _noise(self, noise: torch.Tensor | None, batch: int, generator: torch.Generator | None) -> torch.Tensor:
        """Return the initial noise (B, H, A) float32 on the device: `noise` checked, or N(0, 1) draws."""
        shape = (batch, self.action_horizon, self.action_dim)
        if noise is None:
            device = generator.device if generator is not None else self.device
            return torch.randn(shape, generator=generator, device=device, dtype=torch.float32).to(self.device)
        if not isinstance(noise, torch.Tensor) or tuple(noise.shape) != shape or not noise.is_floating_point():
            found = f"{tuple(noise.shape)} {noise.dtype}" if isinstance(noise, torch.Tensor) else type(noise).__name__
            raise ValueError(f"noise: found {found}, expected {shape} float32 (batch, action_horizon, action_dim)")
        return noise.to(self.device, torch.float32)

    # ------------------------------------------------------------------ robot side

    @property
    def accumulated_time(self) -> bool:
        """Return whether the sampler accumulates its flow times in float32 (openpi) or not (lerobot)."""
        checkpoint = self.prefix.checkpoint
        return checkpoint is None or checkpoint.layout.accumulated_time

    @property
    def layout(self) -> str:
        """Return the checkpoint's layout name (`openpi` or `lerobot`)."""
        checkpoint = self.prefix.checkpoint
        return "openpi" if checkpoint is None else checkpoint.layout.name.value

    def robot_actions(self, actions: torch.Tensor | np.ndarray) -> np.ndarray:
        """Return (..., action_horizon, 7) float32 robot actions: the checkpoint's output transform (openpi's
        quantile un-normalisation then 7 dims, spec 10.8; lerobot's postprocessor, spec 17.4)."""
        if isinstance(actions, torch.Tensor):
            actions = actions.detach().float().cpu().numpy()
        actions = np.asarray(actions)
        if actions.ndim < 1 or actions.shape[-1] != self.action_dim:
            raise ValueError(f"actions: found shape {actions.shape}, expected (..., {self.action_dim})")
        return self.normalization.robot_actions(actions)

    def _require_tokenizer(self) -> PromptTokenizer:
        if self.tokenizer is None:
            raise ValueError("this policy has no tokenizer: pass tokenizer_path= to Pi05Policy.from_checkpoint")
        return self.tokenizer

    def instruction_mask(self, prompt: str, state: np.ndarray | None = None) -> torch.Tensor:
        """Return (1, T) bool: True at the language positions of the prompt's instruction tokens (the state (D,) is
        needed by the discrete-state format, whose prompt carries it)."""
        return self.instruction_masks([prompt], None if state is None else np.asarray(state)[None])

    def instruction_masks(self, prompts: Sequence[str], states: np.ndarray | None) -> torch.Tensor:
        """Return (B, T) bool: each prompt's instruction tokens, tokenised as `tokenize` does."""
        return self.prompt_rows(prompts, states)[2]

    def tokenize(self, prompts: Sequence[str], states: np.ndarray | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Return tokens (B, T) int64 and token_mask (B, T) bool of the prompts, as capture builds them.

        The state (B, D) enters the prompt only in the discrete-state format (normalised by the checkpoint's
        statistics, binned).
        """
        return self.prompt_rows(prompts, states)[:2]

    def prompt_rows(self, prompts: Sequence[str], states: np.ndarray | None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Return tokens (B, T) int64, token_mask and instruction mask (B, T) bool, each prompt encoded once."""
        encoded = self._encode(prompts, states)
        return tuple(torch.from_numpy(np.stack([field(e) for e in encoded]))
                     for field in (lambda e: e.ids, lambda e: e.mask, lambda e: e.instruction_mask()))

    def _encode(self, prompts: Sequence[str], states: np.ndarray | None) -> list[TokenizedPrompt]:
        """Return each prompt tokenised in the checkpoint's format (with its state in the discrete-state one)."""
        tokenizer = self._require_tokenizer()
        if tokenizer.prompt_format is not PromptFormat.DISCRETE_STATE:
            return [tokenizer.tokenize(p) for p in prompts]
        if states is None:
            raise ValueError("the discrete-state prompt carries the state: pass the states with the prompts")
        normalized = self.normalization.normalize_state(np.asarray(states))
        return [tokenizer.tokenize(p, s) for p, s in zip(prompts, normalized)]

    def infer(
        self,
        observation: Mapping[str, Any],
        steering: SteeringArg = None,
        noise: torch.Tensor | np.ndarray | None = None,
        num_steps: int = DEFAULT_STEPS,
    ) -> dict[str, Any]:
        """Return {"actions": (H, 7) float32 (or (B, H, 7) when batched), "policy_timing": {"infer_ms"}}.

        `observation` is openpi's LIBERO dict: "observation/image" and "observation/wrist_image" (H, W, 3)
        uint8, "observation/state" (8,), "prompt" str; a leading batch dim (and a list of prompts) is allowed.
        """
        start = time.perf_counter()
        batch = observation_batch(observation, self.arch.image_size, self.cameras)
        if noise is not None:
            noise = torch.as_tensor(noise, dtype=torch.float32)
            noise = noise if batch.batched else noise[None]
        robot = self.infer_rows(batch, steering, noise, num_steps)
        return {
            "actions": robot if batch.batched else robot[0],
            "policy_timing": {"infer_ms": (time.perf_counter() - start) * 1000.0},
        }

    def infer_rows(
        self,
        batch: ObservationBatch,
        steering: SteeringArg = None,
        noise: torch.Tensor | None = None,
        num_steps: int = DEFAULT_STEPS,
    ) -> np.ndarray:
        """Return (B, H, 7) float32 robot actions of checked observation rows (`observation_batch`, or several
        requests' rows joined by `ObservationBatch.concat`); noise (B, H, A) or None."""
        tokens, token_mask = self.tokenize(batch.prompts, batch.states)
        actions = self.sample_actions(batch.images, batch.image_masks, tokens, token_mask, noise=noise,
                                      num_steps=num_steps, steering=steering)
        return self.robot_actions(actions)

    def warm_up(self, batch: int = 1) -> float:
        """Return the seconds one `infer` of a dummy observation of `batch` frames took.

        With `compiled`, the first call of a batch size compiles its denoising step (seconds to minutes); a
        server calls this before it reports ready, so no request pays it. Needs the tokenizer, as `infer`.
        """
        side = self.arch.image_size
        frames = np.zeros((batch, side, side, 3), dtype=np.uint8)
        state_dim = LIBERO_STATE_DIM
        if self._require_tokenizer().prompt_format is PromptFormat.DISCRETE_STATE:
            state_dim = self.normalization.state_dim or LIBERO_STATE_DIM
        observation = {IMAGE_KEY: frames, WRIST_IMAGE_KEY: frames, STATE_KEY: np.zeros((batch, state_dim)),
                       PROMPT_KEY: ["warm up"] * batch}
        start = time.perf_counter()
        self.infer(observation)
        seconds = time.perf_counter() - start
        logger.info("warmed up at batch %d in %.1f s%s", batch, seconds, " (compiled denoising)" if self.compiled else "")
        return seconds

