"""Trained Stable-Baselines3 models as policies: the policy network, and its normalisation statistics.

Files from users are untrusted: nothing is unpickled unless the user says it trusts the file
(``trust_pickle``, the CLI's ``--trust-pickle``).

Loading a model is a training concept: evaluation uses it here, and the exporter builds its ONNX graph
from the :class:`LoadedPolicy` this module returns.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import pickle
import re
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from tokenize import TokenError
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.policies import ActorCriticPolicy, BasePolicy
from stable_baselines3.common.save_util import load_from_zip_file
from stable_baselines3.sac.policies import SACPolicy
from stable_baselines3.td3.policies import TD3Policy

from embedrl.common import parse_json
from embedrl.train import sb3_archive as archive
from embedrl.train.errors import InvalidModelFileError, UnsupportedModelFileError, UsageError

NORMALIZATION_STEM = "vecnormalize"
"""Statistics next to a model with this name are used unless told otherwise: ``.npz`` (safe), else SB3's
``.pkl`` (opened only when the user trusts it)."""


METADATA_ENTRY = "embedrl.json"
"""An entry embedrl adds to the SB3 zips it trains: ``{"normalization": {"sha256": ...}}`` or
``{"normalization": null}``, so a model separated from its statistics is refused instead of evaluated
wrongly. SB3 ignores it (it reads only ``data`` and ``*.pth``)."""


def normalization_candidates(model: Path) -> list[Path]:
    """Where statistics for ``model`` are looked for, in order: ``<model>_vecnormalize`` (shipped policies
    share a folder), ``vecnormalize`` beside it (an embedrl run), ``<model stem>/vecnormalize`` (RL Zoo's
    ``logs/<algo>/<env>_<n>/<env>.zip`` with ``<env>/vecnormalize.pkl``); ``.npz`` before ``.pkl``."""
    return [
        candidate
        for suffix in (".npz", ".pkl")
        for candidate in (
            model.with_name(f"{model.stem}_{NORMALIZATION_STEM}{suffix}"),
            model.parent / f"{NORMALIZATION_STEM}{suffix}",
            model.parent / model.stem / f"{NORMALIZATION_STEM}{suffix}",
        )
    ]


def vecnormalize_beside(model: Path) -> Path | None:
    """The first of :func:`normalization_candidates` that exists."""
    return next((c for c in normalization_candidates(model) if c.is_file()), None)


def stamp_model(
    model: Path,
    normalization: ObsNormalization | None,
    scenario: str | None = None,
    observation_size: int = 0,
) -> None:
    """Record in ``model``'s zip whether it needs normalisation statistics, and which (their digest), and
    the scenario it was trained on with its observation size (when given)."""
    entry: dict[str, Any] = {
        "normalization": None if normalization is None else {"sha256": normalization.digest()}
    }
    if scenario is not None:
        entry.update(scenario=scenario, observation_size=observation_size)
    with zipfile.ZipFile(model, "a") as zf:
        if METADATA_ENTRY in zf.namelist():
            raise ValueError(f"{model} already has {METADATA_ENTRY}")
        zf.writestr(METADATA_ENTRY, json.dumps(entry, sort_keys=True))


def model_metadata(model: Path) -> dict[str, Any] | None:
    """``model``'s :data:`METADATA_ENTRY` (None for models embedrl did not train)."""
    try:
        with zipfile.ZipFile(model) as zf:
            if METADATA_ENTRY not in zf.namelist():
                return None
            entry = parse_json(zf.read(METADATA_ENTRY))
    except (zipfile.BadZipFile, ValueError) as exc:
        raise InvalidModelFileError(f"{model}: unreadable {METADATA_ENTRY} ({exc})") from None
    if not isinstance(entry, dict) or not isinstance(entry.get("normalization", {}), dict | None):
        raise InvalidModelFileError(f"{model}: {METADATA_ENTRY} is not what embedrl writes")
    return entry


@dataclass(frozen=True)
class ObsNormalization:
    """VecNormalize's observation transform: ``clip((obs - mean) / sqrt(var + eps), -clip, clip)``."""

    mean: np.ndarray
    var: np.ndarray
    epsilon: float
    clip: float

    def apply(self, obs: np.ndarray) -> np.ndarray:
        """Exactly what VecNormalize.normalize_obs computes (float64), as float32."""
        out = np.clip((obs - self.mean) / np.sqrt(self.var + self.epsilon), -self.clip, self.clip)
        return np.asarray(out, dtype=np.float32)

    def digest(self) -> str:
        """SHA-256 of the statistics (float64 mean, var, epsilon, clip): the same from .npz or .pkl."""
        h = hashlib.sha256()
        for part in (self.mean, self.var, np.float64(self.epsilon), np.float64(self.clip)):
            h.update(np.ascontiguousarray(part, dtype="<f8").tobytes())
        return h.hexdigest()


@dataclass(frozen=True)
class LoadedPolicy:
    """An SB3 policy ready for export and for reference predictions.

    A recurrent policy (RecurrentPPO's) carries its LSTM state from call to call: a batch is consecutive
    steps of one episode, and :meth:`reset` starts the next episode from zero state, as SB3's ``predict``
    does with ``episode_start``.
    """

    policy: BasePolicy
    observation_space: spaces.Box
    action_space: spaces.Box
    normalization: ObsNormalization | None
    normalization_file: Path | None = None
    _memory: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    @property
    def kind(self) -> str:
        return type(self.policy).__name__

    @property
    def recurrent(self) -> bool:
        return hasattr(self.policy, "lstm_actor")

    def reset(self) -> None:
        """A new episode: the LSTM state back to zero (nothing for a policy without memory)."""
        self._memory.clear()

    def predict(self, obs: np.ndarray) -> np.ndarray:
        """``predict(deterministic=True)`` on a batch of raw observations, normalised as in training (a
        recurrent policy: the rows in order, the state carried)."""
        x = obs if self.normalization is None else self.normalization.apply(obs)
        if not self.recurrent:
            actions, _ = self.policy.predict(x, deterministic=True)
            return np.asarray(actions, dtype=np.float32)
        rows = np.asarray(x, np.float32).reshape(-1, self.observation_space.shape[0])
        out = []
        for row in rows:
            start = np.array(["state" not in self._memory])
            action, self._memory["state"] = self.policy.predict(
                row[None], self._memory.get("state"), start, deterministic=True
            )
            out.append(np.asarray(action, np.float32).reshape(-1))
        return np.asarray(out, np.float32).reshape(*np.shape(obs)[:-1], -1)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.predict(obs)


MAX_MODEL_BYTES = 64 * 2**20
MAX_PARAMETERS = 4_000_000
"""The most weights a model's networks may declare (actor, critics and value net together)."""
MAX_WIDTH = 65_536
"""The widest layer a model may declare."""
"""The largest uncompressed archive entry read by default (a control policy is far smaller)."""


class _NoOptimizer:
    """The optimizer of a policy loaded to infer: none (a torch optimizer would import torch's compiler,
    1-2 s of every process that loads a policy)."""

    def __init__(self, params: Any, **kwargs: Any) -> None:
        del params, kwargs


def load_sb3(
    path: Path,
    vecnormalize: Path | None = None,
    trust_pickle: bool = False,
    max_bytes: int = MAX_MODEL_BYTES,
    max_parameters: int = MAX_PARAMETERS,
) -> LoadedPolicy:
    """Load the policy of an SB3 ``.zip`` (any algorithm) without its algorithm or environment.

    Normalisation statistics: ``vecnormalize`` if given, else the first of
    :func:`normalization_candidates`. A model embedrl trained says whether it needs statistics and which
    (:data:`METADATA_ENTRY`): missing or different ones are refused. Nothing from the files is unpickled
    (:mod:`embedrl.train.sb3_archive`) unless ``trust_pickle``. Sets torch to one thread: the policy runs
    one observation at a time.
    """
    if not path.is_file():
        raise InvalidModelFileError(f"{path}: no such file")
    _check_archive_size(path, max_bytes)
    try:
        data, params, _ = load_from_zip_file(
            path, load_data=trust_pickle, device="cpu", print_system_info=False
        )
    except (zipfile.BadZipFile, KeyError, ValueError, EOFError, RuntimeError, pickle.UnpicklingError) as exc:
        raise InvalidModelFileError(
            f"{path}: not a readable Stable-Baselines3 model ({_one_line(exc)})"
        ) from None
    if params is None or "policy" not in params:
        raise InvalidModelFileError(f"{path}: the archive has no policy parameters")
    if trust_pickle:
        assert data is not None
        cls = data.get("policy_class")
        obs_space, act_space = data.get("observation_space"), data.get("action_space")
        raw_kwargs = data.get("policy_kwargs", {})
        if not isinstance(raw_kwargs, dict):
            raise InvalidModelFileError(f"{path}: policy_kwargs is not a dict")
        kwargs = dict(raw_kwargs)
    else:
        data = archive.read_data(path)
        cls = archive.policy_class(path, data)
        obs_space, act_space = archive.box(path, data, "observation"), archive.box(path, data, "action")
        kwargs = archive.policy_kwargs(path, data)
    if not isinstance(cls, type) or not issubclass(cls, (TD3Policy, SACPolicy, ActorCriticPolicy)):
        name = getattr(cls, "__name__", repr(cls))
        raise UnsupportedModelFileError(
            f"{path}: policy class {name} is not supported; supported: TD3Policy (TD3, DDPG), "
            "SACPolicy (SAC), ActorCriticPolicy (PPO, A2C), RecurrentActorCriticPolicy (RecurrentPPO)"
        )
    for role, space in (("observation", obs_space), ("action", act_space)):
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise UnsupportedModelFileError(f"{path}: {role} space {space} is not supported; need a 1-D Box")
    assert isinstance(obs_space, spaces.Box) and isinstance(act_space, spaces.Box)
    if data.get("use_sde") or kwargs.get("use_sde"):
        raise UnsupportedModelFileError(f"{path}: policies with gSDE (use_sde=True) are not supported")
    from sb3_contrib.common.recurrent.policies import RecurrentActorCriticPolicy

    recurrent = issubclass(cls, RecurrentActorCriticPolicy)
    _check_architecture(path, kwargs, obs_space.shape[0], act_space.shape[0], max_parameters, recurrent)
    kwargs.update(optimizer_class=_NoOptimizer, optimizer_kwargs={})
    try:
        policy = cls(obs_space, act_space, lambda _: 0.0, **kwargs)
    except TypeError as exc:
        raise UnsupportedModelFileError(f"{path}: policy_kwargs do not fit {cls.__name__} ({exc})") from None
    try:
        policy.load_state_dict(params["policy"])  # type: ignore[arg-type]
    except RuntimeError as exc:
        raise InvalidModelFileError(f"{path}: policy parameters do not match the policy ({exc})") from None
    policy.set_training_mode(False)
    # One observation at a time through a network this small: one thread is fastest, and extra threads
    # contend on a busy machine (the recurrent export's verification: ~3x longer with torch's default).
    torch.set_num_threads(1)
    stats_file, normalization = _matching_normalization(path, vecnormalize, obs_space, trust_pickle)
    return LoadedPolicy(policy, obs_space, act_space, normalization, stats_file)


WEIGHTS_ONLY_DETAIL = re.compile(r"WeightsUnpickler error:\s*(.*?)\s*(Check the documentation|$)", re.S)


def _one_line(exc: BaseException) -> str:
    """An error from torch or zipfile as one line: torch's weights-only refusal (a page of advice about
    ``weights_only=False``, which embedrl never uses on untrusted files) becomes its cause."""
    text = str(exc)
    found = WEIGHTS_ONLY_DETAIL.search(text)
    if found:
        text = f"policy.pth holds more than tensors: {found.group(1)}"
    return " ".join(text.split())


MAX_LSTM_LAYERS = 8


def _check_architecture(
    path: Path,
    kwargs: dict[str, Any],
    obs_dim: int,
    act_dim: int,
    max_parameters: int,
    recurrent: bool = False,
) -> None:
    """Refuse, before a single weight is allocated, layer widths that are not 1..MAX_WIDTH and networks
    whose weights would exceed ``max_parameters`` (the actor, every critic and the value net, counted
    from ``net_arch`` and the spaces; a recurrent policy's LSTMs as well)."""
    for role, dim in (("observation", obs_dim), ("action", act_dim)):
        if not 1 <= dim <= MAX_WIDTH:
            raise InvalidModelFileError(f"{path}: an {role} space of {dim:,} values is not supported")
    arch = kwargs.get("net_arch", [64, 64])
    nets = arch if isinstance(arch, dict) else {"pi": arch, "qf": arch, "vf": arch}
    if not isinstance(nets, dict) or not all(isinstance(w, list | tuple) for w in nets.values()):
        raise InvalidModelFileError(
            f"{path}: net_arch {arch!r} is not a list of layer widths or a dict of them"
        )
    widths = [w for layers in nets.values() for w in layers]
    if not all(isinstance(w, int) and not isinstance(w, bool) and 1 <= w <= MAX_WIDTH for w in widths):
        raise InvalidModelFileError(
            f"{path}: net_arch {arch!r}: layer widths must be integers in 1..{MAX_WIDTH:,}"
        )
    n_critics = kwargs.get("n_critics", 2)
    if not isinstance(n_critics, int) or not 1 <= n_critics <= 16:
        raise InvalidModelFileError(f"{path}: n_critics {n_critics!r} is not within 1..16")

    def chain(sizes: list[int]) -> int:
        return sum(a * b + b for a, b in itertools.pairwise(sizes))

    lstm = 0
    latent = obs_dim
    if recurrent:
        hidden, layers = kwargs.get("lstm_hidden_size", 256), kwargs.get("n_lstm_layers", 1)
        for key, value, top in (
            ("lstm_hidden_size", hidden, MAX_WIDTH),
            ("n_lstm_layers", layers, MAX_LSTM_LAYERS),
        ):
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= top:
                raise InvalidModelFileError(f"{path}: {key} {value!r} is not within 1..{top:,}")
        if kwargs.get("lstm_kwargs"):
            raise UnsupportedModelFileError(
                f"{path}: lstm_kwargs {kwargs['lstm_kwargs']!r} are not supported"
            )
        per_net = 4 * (hidden * (obs_dim + hidden) + 2 * hidden) + (layers - 1) * 4 * (
            2 * hidden * hidden + 2 * hidden
        )
        lstm = per_net * (2 if kwargs.get("enable_critic_lstm", True) else 1)
        latent = hidden
    parameters = (
        lstm
        + chain([latent, *nets.get("pi", []), 2 * act_dim])
        + n_critics * chain([obs_dim + act_dim, *nets.get("qf", []), 1])
        + chain([latent, *nets.get("vf", []), 1])
    )
    if parameters > max_parameters:
        raise InvalidModelFileError(
            f"{path}: net_arch {arch!r} declares about {parameters:,} parameters; they exceed the limit of "
            f"{max_parameters:,} (--max-params raises it)"
        )


def _check_archive_size(path: Path, max_bytes: int) -> None:
    """Refuse an archive whose entries would unpack to more than ``max_bytes`` (before reading them)."""
    try:
        with zipfile.ZipFile(path) as zf:
            total = sum(info.file_size for info in zf.infolist())
    except zipfile.BadZipFile as exc:
        raise InvalidModelFileError(f"{path}: not a readable Stable-Baselines3 model ({exc})") from None
    if total > max_bytes:
        raise InvalidModelFileError(
            f"{path}: unpacks to {total / 2**20:.1f} MB, above the {max_bytes / 2**20:.0f} MB limit "
            "(--max-model-mb raises it)"
        )


def _matching_normalization(
    path: Path, given: Path | None, obs_space: spaces.Box, trust_pickle: bool
) -> tuple[Path | None, ObsNormalization | None]:
    metadata = model_metadata(path)
    found = given or vecnormalize_beside(path)
    if metadata is not None and metadata.get("normalization") is None:
        if given is not None:
            raise InvalidModelFileError(f"{path} was trained without observation normalisation; drop {given}")
        return None, None  # statistics beside it belong to another model
    normalization = load_normalization(found, obs_space, trust_pickle) if found else None
    if metadata is None:
        return (found if normalization else None), normalization
    expected = metadata["normalization"]["sha256"]
    if normalization is None:
        looked = ", ".join(str(c) for c in normalization_candidates(path))
        raise InvalidModelFileError(
            f"{path} was trained with observation normalisation but its statistics are "
            + (f"disabled in {found}" if found else f"missing (looked for {looked})")
            + "; give them with --vecnormalize FILE"
        )
    if normalization.digest() != expected:
        raise InvalidModelFileError(
            f"{found} are not {path}'s normalisation statistics (sha256 {normalization.digest()[:12]}..., "
            f"the model was trained with {expected[:12]}...)"
        )
    return found, normalization


def normalization_of(stats: Any) -> ObsNormalization:
    """The observation transform of a VecNormalize (as :func:`save_normalization` writes it)."""
    rms = stats.obs_rms
    return ObsNormalization(
        np.asarray(rms.mean, np.float64),
        np.asarray(rms.var, np.float64),
        float(stats.epsilon),
        float(stats.clip_obs),
    )


def save_normalization(stats: Any, path: Path) -> None:
    """VecNormalize's observation statistics as ``.npz`` (plain arrays: safe to open anywhere)."""
    rms = stats.obs_rms
    np.savez(
        path,
        mean=np.asarray(rms.mean, np.float64),
        var=np.asarray(rms.var, np.float64),
        epsilon=np.float64(stats.epsilon),
        clip_obs=np.float64(stats.clip_obs),
        norm_obs=np.bool_(stats.norm_obs),
    )


def load_normalization(
    path: Path, obs_space: spaces.Box, trust_pickle: bool = False
) -> ObsNormalization | None:
    """Statistics from ``.npz``; from SB3's ``.pkl`` only with ``trust_pickle`` (unpickling runs code)."""
    if not path.is_file():
        raise InvalidModelFileError(f"{path}: no such file (normalisation statistics)")
    if path.suffix == ".npz":
        try:
            _check_npz_headers(path, obs_space.shape[0])
            with np.load(path, allow_pickle=False) as f:
                mean, var = np.asarray(f["mean"], np.float64), np.asarray(f["var"], np.float64)
                epsilon, clip, enabled = float(f["epsilon"]), float(f["clip_obs"]), bool(f["norm_obs"])
        except (
            OSError,
            KeyError,
            ValueError,
            TypeError,
            EOFError,
            SyntaxError,
            TokenError,
            zipfile.BadZipFile,
        ) as exc:
            # a damaged .npy header fails in numpy's parser of it: SyntaxError or TokenError
            raise InvalidModelFileError(
                f"{path}: not normalisation statistics written by embedrl ({exc})"
            ) from None
    else:
        try:
            with path.open("rb") as f:
                stats: Any = pickle.load(f) if trust_pickle else _StatsUnpickler(f).load()
            rms, enabled = stats.obs_rms, bool(stats.norm_obs)
            mean, var = np.asarray(rms.mean, np.float64), np.asarray(rms.var, np.float64)
            epsilon, clip = float(stats.epsilon), float(stats.clip_obs)
        except _Refused as exc:
            raise UnsupportedModelFileError(
                f"{path} is a pickle that needs more than VecNormalize's statistics to open ({exc}): opening "
                f"it could run code from it. {archive.TRUST_HINT}"
            ) from None
        except (pickle.UnpicklingError, EOFError, AttributeError, ValueError, TypeError) as exc:
            raise InvalidModelFileError(f"{path}: not VecNormalize statistics saved by SB3 ({exc})") from None
    if not enabled:
        return None
    if mean.shape != obs_space.shape or var.shape != obs_space.shape:
        raise InvalidModelFileError(
            f"{path}: statistics of shape {mean.shape} do not fit observations {obs_space.shape}"
        )
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
        raise InvalidModelFileError(f"{path}: statistics contain non-finite or negative values")
    return ObsNormalization(mean, var, epsilon, clip)


NPZ_SHAPES = {"mean": 1, "var": 1, "epsilon": 0, "clip_obs": 0, "norm_obs": 0}
"""The arrays of an embedrl statistics file and their ranks."""


def _check_npz_headers(path: Path, obs_dim: int) -> None:
    """Each array's shape and type from its ``.npy`` header, before any array is read: numbers only,
    the vectors of ``obs_dim`` values, the others scalars (ValueError otherwise)."""
    with zipfile.ZipFile(path) as zf:
        for name, rank in NPZ_SHAPES.items():
            with zf.open(f"{name}.npy") as member:
                version = np.lib.format.read_magic(member)
                read_header = (
                    np.lib.format.read_array_header_1_0
                    if version == (1, 0)
                    else np.lib.format.read_array_header_2_0
                )
                shape, _, dtype = read_header(member)
            expected = (obs_dim,) if rank else ()
            if dtype.kind not in "fiub":
                raise ValueError(f"{name} has dtype {dtype}; numbers are expected")
            if tuple(shape) != expected:
                values = math.prod(shape)
                raise ValueError(f"{name} has shape {tuple(shape)} ({values:,} values); expected {expected}")


class _Refused(pickle.UnpicklingError):
    """A pickle asked for something :class:`_StatsUnpickler` does not give."""


class _Inert:
    """Stands in for any SB3, gymnasium or NumPy random object of a VecNormalize pickle: it only keeps
    the state it is given, so no class's own code runs."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        if isinstance(state, tuple) and len(state) == 2:  # (dict, slots)
            state = {**(state[0] or {}), **(state[1] or {})}
        if isinstance(state, dict):
            self.__dict__.update(state)

    def __call__(self, *args: Any, **kwargs: Any) -> _Inert:
        return _Inert()


class _StatsUnpickler(pickle.Unpickler):
    """Reads SB3's ``vecnormalize.pkl`` (e.g. RL Zoo's) without running code from it: NumPy arrays and
    dtypes are rebuilt by NumPy's own reconstructors; every SB3, gymnasium or NumPy random class becomes
    an :class:`_Inert` holder of its state; anything else is refused."""

    REAL = frozenset(
        {
            ("copyreg", "_reconstructor"),
            ("builtins", "object"),
            ("numpy", "ndarray"),
            ("numpy", "dtype"),
            ("numpy.core.multiarray", "_reconstruct"),
            ("numpy._core.multiarray", "_reconstruct"),
            ("numpy.core.multiarray", "scalar"),
            ("numpy._core.multiarray", "scalar"),
            ("collections", "OrderedDict"),
        }
    )
    INERT_PACKAGES = ("stable_baselines3.", "gymnasium.", "gym.", "numpy.random.")

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self.REAL:
            return super().find_class(module, name)
        if module.startswith(self.INERT_PACKAGES):
            return _Inert
        raise _Refused(f"{module}.{name}")


def _convert(argv: list[str]) -> int:
    """``python -m embedrl.train.models FILE.pkl``: write FILE.npz from SB3 statistics you trust."""
    if len(argv) != 1 or not argv[0].endswith(".pkl"):
        print(
            "usage: python -m embedrl.train.models STATISTICS.pkl  (unpickles it: only for files you trust)"
        )
        return 2
    source = Path(argv[0])
    with source.open("rb") as f:
        stats = pickle.load(f)
    save_normalization(stats, source.with_suffix(".npz"))
    print(f"wrote {source.with_suffix('.npz')}")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(_convert(sys.argv[1:]))


def load_model_policy(
    path: Path, trust_pickle: bool = False, vecnormalize: Path | None = None
) -> _OneObservation:
    """A trained SB3 model as a deterministic policy, with its normalisation statistics (``vecnormalize``,
    else found beside it; refused if they are missing or not the model's own).

    Nothing is unpickled unless ``trust_pickle`` (see :mod:`embedrl.train.sb3_archive`)."""
    if path.suffix != ".zip":
        raise UsageError(f"cannot evaluate {path}: give a Stable-Baselines3 model (.zip)")
    return _OneObservation(load_sb3(path, vecnormalize, trust_pickle))


class _OneObservation:
    """A loaded policy on one observation at a time; ``reset`` starts an episode (a recurrent policy's
    zero state)."""

    def __init__(self, loaded: LoadedPolicy) -> None:
        self.loaded = loaded
        self.reset = loaded.reset

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return np.asarray(self.loaded.predict(obs.reshape(1, -1))[0], np.float32)
