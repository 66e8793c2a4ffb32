"""Build generated C with ``make -C runtime_c`` and the system compiler; load it through ctypes."""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from embedrl.common import owned_temporary_folder
from embedrl.export.errors import BuildError

RUNTIME_C = Path(__file__).resolve().parents[1] / "runtime_c"
"""The make project that builds generated policies: beside this package in the repository, and inside
the ``embedrl`` package (as package data) in an installed wheel."""


FIT_REFUSAL = re.compile(r"^([\w-]+) \((.+)\): (\S+) does not fit the part's memory: (.+)$", re.MULTILINE)
"""The one line with which a Cortex-M link (``runtime_c/cortex_m/fit.sh``) refuses an image too large for its
part: target, part, image, and each overflowed region's bytes needed against available."""


def make(
    target: str, c_dir: Path, build_dir: Path, opt: str | None = None, extra: dict[str, str] | None = None
) -> None:
    """Run ``make -C runtime_c TARGET POLICY_DIR=c_dir BUILD_DIR=build_dir [OPT=opt] [NAME=VALUE ...]``.

    Folders and files with whitespace in their path (``extra`` values naming a file included) reach make
    through links without any. Errors carry the last lines of make's output.
    """
    if not (RUNTIME_C / "Makefile").is_file():
        raise BuildError(f"{RUNTIME_C}/Makefile not found: the installation is incomplete")
    build_dir.mkdir(parents=True, exist_ok=True)
    extra = dict(extra or {})
    files = {k: Path(v) for k, v in extra.items() if Path(v).is_absolute() and Path(v).is_file()}
    folders = [c_dir.resolve(), build_dir.resolve(), *(p.resolve().parent for p in files.values())]
    with _without_spaces(*folders) as (policy_dir, out_dir, *file_dirs):
        for (key, path), folder in zip(files.items(), file_dirs, strict=True):
            extra[key] = str(folder / path.name)
        cmd = [
            "make",
            "--no-print-directory",
            "-C",
            str(RUNTIME_C),
            target,
            f"POLICY_DIR={policy_dir}",
            f"BUILD_DIR={out_dir}",
        ]
        if opt is not None:
            cmd.append(f"OPT={opt}")
        cmd += [f"{k}={v}" for k, v in extra.items()]
        result = subprocess.run(cmd, capture_output=True, text=True, env=_own_make_env())
    if result.returncode != 0:
        refused = FIT_REFUSAL.search(result.stderr)
        if refused:  # an image too large for its part: the link's one line says all
            raise BuildError(refused.group(0))
        tail = "\n".join((result.stdout + result.stderr).strip().splitlines()[-15:])
        raise BuildError(f"building the generated C failed (make {target}):\n{tail}")


def _own_make_env() -> dict[str, str]:
    """This environment without a calling make's variables: run from a Makefile target (``make
    targets-example OUT=x``), the caller's command-line variables would reach runtime_c's own make
    through MAKEFLAGS and override its variables of the same name."""
    return {
        k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL", "MAKEOVERRIDES")
    }


@contextlib.contextmanager
def _without_spaces(*folders: Path) -> Iterator[list[Path]]:
    """``folders`` as make can take them: a folder whose path has whitespace (make splits words on it)
    is reached through a symbolic link in a temporary folder without any; ``..`` from a link resolves
    in the real folder, so the export's layout (``c/../interface.json``) still holds."""
    if not any(any(c.isspace() for c in str(f)) for f in folders):
        yield list(folders)
        return
    base = tempfile.gettempdir()
    with owned_temporary_folder("embedrl-make-", Path(base if " " not in base else "/tmp")) as links:
        aliases = []
        for index, folder in enumerate(folders):
            alias = links / f"f{index}"
            alias.symlink_to(folder, target_is_directory=True)
            aliases.append(alias)
        yield aliases


def compiler(target: str = "host", goal: str = "flags") -> dict[str, str]:
    """The compiler command and flags the Makefile uses for ``target`` (``host`` or a Cortex-M target of
    ``runtime_c/cortex_m/targets.mk``), and the compiler's version line; ``goal`` ``coverage-flags``: those
    of the coverage builds (clang's, ``make coverage`` and ``coverage-node``)."""
    flags = subprocess.run(
        ["make", "--no-print-directory", "-s", "-C", str(RUNTIME_C), goal, f"TARGET={target}"],
        env=_own_make_env(),
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    cc = flags.split()[0]
    version = subprocess.run([cc, "--version"], capture_output=True, text=True, check=True).stdout
    return {"command": flags, "version": version.splitlines()[0]}


def object_size(obj: Path) -> dict[str, int]:
    """text, data and bss bytes of an object file (binutils ``size``, Berkeley format)."""
    out = subprocess.run(["size", str(obj)], capture_output=True, text=True, check=True).stdout
    text, data, bss = (int(v) for v in re.split(r"\s+", out.splitlines()[1].strip())[:3])
    return {"text": text, "data": data, "bss": bss}


class CPolicy:
    """A compiled policy: ``policy(obs) -> action``; ``status`` is the last return code."""

    def __init__(self, library: Path, name: str, obs_dim: int, act_dim: int) -> None:
        self._lib = ctypes.CDLL(str(library))
        self._step = getattr(self._lib, f"{name}_step")
        ptr = ctypes.POINTER(ctypes.c_float)
        self._step.argtypes = [ptr, ptr]
        self._step.restype = ctypes.c_int
        self._batch = getattr(self._lib, f"{name}_step_batch")
        self._batch.argtypes = [ctypes.c_int, ptr, ptr, ctypes.POINTER(ctypes.c_int)]
        self._batch.restype = ctypes.c_int
        self.reset = getattr(self._lib, f"{name}_reset")
        """Zero the recurrent state (a new episode); nothing for a policy without memory."""
        self.reset.argtypes, self.reset.restype = [], None
        self._ptr = ptr
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self._act = np.zeros(act_dim, dtype=np.float32)
        self._act_ptr = self._act.ctypes.data_as(ptr)
        self.status = 0

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(obs, dtype=np.float32).reshape(self.obs_dim)
        self.status = int(self._step(x.ctypes.data_as(self._ptr), self._act_ptr))
        return self._act.copy()

    def batch(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Actions and return codes for every row of ``obs``, by ``{name}_step_batch`` (each row bit for
        bit as ``{name}_step`` answers it)."""
        x = np.ascontiguousarray(obs, dtype=np.float32).reshape(-1, self.obs_dim)
        acts = np.zeros((len(x), self.act_dim), dtype=np.float32)
        codes = np.zeros(len(x), dtype=np.intc)
        if len(x):
            self._batch(
                len(x), x.ctypes.data_as(self._ptr), acts.ctypes.data_as(self._ptr),
                codes.ctypes.data_as(ctypes.POINTER(ctypes.c_int)),
            )  # fmt: skip
        return acts, codes.astype(np.int32)

    def rows(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`batch`, one ``{name}_step`` call per row."""
        acts = np.zeros((len(obs), self.act_dim), dtype=np.float32)
        codes = np.zeros(len(obs), dtype=np.int32)
        for i, row in enumerate(obs):
            acts[i] = self(row)
            codes[i] = self.status
        return acts, codes
