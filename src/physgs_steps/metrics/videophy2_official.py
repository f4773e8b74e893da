"""The official VideoPhy-2 auto-rater, run as a subprocess in its own environment.

The rater pins transformers 4.28.1 and needs a CUDA GPU, so it cannot load in this project's
environment; it is run the way its README runs it, once per task::

    <python> VIDEOPHY2/inference.py --input_csv IN --output_csv OUT --task sa|pc \\
        --checkpoint <videophy_2_auto> --num_frames 32

Configured (``metrics.videophy2.official``) either by

* ``command``: a shell command template with ``{input_csv}``, ``{output_csv}`` and ``{task}``
  (and optionally ``{checkpoint}``, ``{num_frames}``, ``{repo}``, ``{python}``; every value
  is shell-quoted), e.g. ``conda run -n videophy python /opt/videophy/VIDEOPHY2/inference.py
  --input_csv {input_csv} --output_csv {output_csv} --task {task} --checkpoint /w/videophy_2_auto``;
* or ``python`` (the rater environment's interpreter), ``repo`` (a checkout of the VideoPhy
  repository, or its ``VIDEOPHY2`` folder) and ``checkpoint`` (the ``videophy_2_auto`` folder).

Input CSV (written here): columns ``caption`` (the scene prompt) and ``videopath`` (the
absolute path of video.mp4); the ``pc`` task ignores the caption. Output CSV (written by the
rater): the input columns, a leading index column and ``score``, a number 0-5; 0 is what the
rater writes when it cannot read its model's answer and is reported as no rating.

A rater that is missing, exits non-zero, runs past ``timeout_s`` (its process group is
killed) or writes no or malformed output gives a null score whose reason carries the tail of
its stderr; it never gives a number.
"""
from __future__ import annotations

import csv
import logging
import math
import os
import shlex
import shutil
import signal
import string
import subprocess
import time
from pathlib import Path

from ..errors import ConfigError
from .scores import tail
from .videophy2 import BACKENDS, not_rated, rated

KEY = "metrics.videophy2.official"
REQUIRED = ("input_csv", "output_csv", "task")
OPTIONAL = ("checkpoint", "num_frames", "repo", "python")
BACKEND = BACKENDS["official"]
_VERSION_CACHE: dict[tuple, dict] = {}


def configured(oc: dict) -> bool:
    """Whether any way of running the official rater is set."""
    return any(oc.get(k) for k in ("command", "python", "repo", "checkpoint"))


def validate(oc: dict) -> None:
    """Check the section's consistency before any work (ConfigError naming the key)."""
    cmd = oc.get("command")
    if cmd:
        if not isinstance(cmd, str):
            raise ConfigError(f"{KEY}.command", f"must be a string, got {type(cmd).__name__}")
        try:
            names = [f for _, f, _, _ in string.Formatter().parse(cmd) if f is not None]
        except ValueError as e:
            raise ConfigError(f"{KEY}.command", f"not a valid template ({e}); write literal braces as {{{{ }}}}") from None
        unknown = sorted({n for n in names if n not in REQUIRED + OPTIONAL})
        if unknown:
            raise ConfigError(f"{KEY}.command", f"unknown placeholder(s) {unknown}; allowed: "
                                                f"{', '.join('{' + n + '}' for n in REQUIRED + OPTIONAL)}")
        missing = [n for n in REQUIRED if n not in names]
        if missing:
            raise ConfigError(f"{KEY}.command", f"the template lacks {', '.join('{' + n + '}' for n in missing)} "
                                                f"(the rater is run once per task with its own input and output CSV)")
        unset = [n for n in names if n in ("checkpoint", "repo", "python") and not oc.get(n)]
        if unset:
            raise ConfigError(f"{KEY}.command", f"uses {', '.join('{' + n + '}' for n in unset)} but "
                                                f"{', '.join(f'{KEY}.{n}' for n in unset)} is not set")
    else:
        missing = [f"{KEY}.{k}" for k in ("python", "repo", "checkpoint") if not oc.get(k)]
        if missing:
            raise ConfigError(missing[0], f"the official rater needs {KEY}.command, or all of {KEY}.python, "
                                          f".repo and .checkpoint; missing: {', '.join(missing)}")
    t = oc.get("timeout_s", 1800)
    if not isinstance(t, (int, float)) or not t > 0:
        raise ConfigError(f"{KEY}.timeout_s", f"must be a positive number of seconds, got {t!r}")


def _script(repo: str) -> Path:
    r = Path(os.path.expanduser(repo))
    return r / "inference.py" if (r / "inference.py").is_file() else r / "VIDEOPHY2" / "inference.py"


def _missing_parts(oc: dict) -> str | None:
    """Why the configured rater is not on this machine, or None."""
    if oc.get("command"):
        return None   # whatever the template runs is checked by running it
    py = os.path.expanduser(oc["python"])
    if (os.sep in py and not os.access(py, os.X_OK)) or (os.sep not in py and shutil.which(py) is None):
        return f"{KEY}.python {oc['python']!r} is not an executable on this machine"
    if not _script(oc["repo"]).is_file():
        return (f"{KEY}.repo {oc['repo']!r} has no VIDEOPHY2/inference.py (clone "
                f"https://github.com/Hritikbansal/videophy there)")
    if not Path(os.path.expanduser(oc["checkpoint"])).is_dir():
        return f"{KEY}.checkpoint {oc['checkpoint']!r} is not a folder (git clone https://huggingface.co/videophysics/videophy_2_auto)"
    return None


def command(oc: dict, task: str, input_csv: str, output_csv: str) -> tuple[list[str] | str, str | None]:
    """(argv list, or a shell command string for a template; working folder or None)."""
    n = int(oc.get("num_frames", 32))
    if oc.get("command"):
        values = {"input_csv": input_csv, "output_csv": output_csv, "task": task, "num_frames": n,
                  "checkpoint": oc.get("checkpoint"), "repo": oc.get("repo"), "python": oc.get("python")}
        quoted = {k: shlex.quote(os.path.expanduser(str(v))) for k, v in values.items() if v is not None}
        return oc["command"].format(**quoted), None
    script = _script(oc["repo"])
    argv = [os.path.expanduser(oc["python"]), str(script), "--input_csv", input_csv, "--output_csv", output_csv,
            "--task", task, "--checkpoint", os.path.expanduser(oc["checkpoint"]), "--num_frames", str(n)]
    return argv, str(script.parent)


def rater_version(oc: dict) -> dict:
    """The configured label and the git commits of the rater's checkout and checkpoint (when git repos)."""
    key = (oc.get("version"), oc.get("repo"), oc.get("checkpoint"))
    if key not in _VERSION_CACHE:
        _VERSION_CACHE[key] = {"label": oc.get("version"),
                               "repo_commit": _git_commit(oc.get("repo")),
                               "checkpoint_commit": _git_commit(oc.get("checkpoint"))}
    return _VERSION_CACHE[key]


def _git_commit(path: str | None) -> str | None:
    if not path:
        return None
    p = Path(os.path.expanduser(path))
    top = p if (p / ".git").exists() else p.parent if (p.parent / ".git").exists() else None
    if top is None or shutil.which("git") is None:
        return None
    try:
        r = subprocess.run(["git", "-C", str(top), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return (r.stdout.strip() or None) if r.returncode == 0 else None


def write_input_csv(path: str, video: str, caption: str) -> None:
    """The rater's input: columns caption, videopath (one row: our video)."""
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["caption", "videopath"])
        w.writerow([caption, video])


class Malformed(Exception):
    """The rater's output CSV cannot be read as a rating of our video."""


def read_output_csv(path: str, video: str) -> tuple[int | None, str, str | None]:
    """(rating 1-5 or None, the raw score cell, why there is no rating) of ``video``.

    Raises:
        Malformed when the file is missing, has no ``score``/``videopath`` column, has no
        row for the video, or the score is not a whole number from 0 to 5.
    """
    p = Path(path)
    if not p.is_file():
        raise Malformed(f"the rater exited with status 0 but wrote no output CSV ({p.name})")
    try:
        with open(p, newline="") as f:
            rows = list(csv.DictReader(f))
            header = rows[0].keys() if rows else []
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise Malformed(f"cannot read its output CSV: {e}") from None
    if "score" not in header or "videopath" not in header:
        raise Malformed(f"its output CSV has no 'score' and 'videopath' columns (columns: {list(header)})")
    mine = [r for r in rows if os.path.normpath(str(r.get("videopath") or "")) == os.path.normpath(video)]
    if len(mine) != 1:
        raise Malformed(f"its output CSV has {len(mine)} rows for {video} (expected 1; {len(rows)} rows in all)")
    cell = str(mine[0].get("score") or "").strip()
    try:
        score = float(cell)
    except ValueError:
        raise Malformed(f"its score {cell!r} is not a number") from None
    if not math.isfinite(score) or score != int(score) or not 0 <= score <= 5:
        raise Malformed(f"its score {cell!r} is not a whole number from 0 to 5")
    if score == 0:
        return None, cell, "the rater could not read its model's answer (it writes score 0 then; see its output)"
    return int(score), cell, None


def run_task(task: str, video: str, caption: str, oc: dict, mapping: str, workdir: str, log: logging.Logger) -> dict:
    """The score entry of ``task`` (``sa`` or ``pc``) of ``video`` from the official rater."""
    version = rater_version(oc)
    missing = _missing_parts(oc)
    if missing:
        return not_rated(task, f"the VideoPhy2 rater is not installed: {missing}", BACKEND, rater_version=version)
    if task == "sa" and not caption:
        return not_rated(task, "no caption: the scene has no prompt and metrics.text is not set", BACKEND)
    in_csv = str(Path(workdir) / "input.csv")
    out_csv = str(Path(workdir) / f"output_{task}.csv")
    write_input_csv(in_csv, video, caption)
    cmd, cwd = command(oc, task, in_csv, out_csv)
    shown = cmd if isinstance(cmd, str) else shlex.join(cmd)
    env = os.environ | {str(k): str(v) for k, v in (oc.get("env") or {}).items()}
    timeout = float(oc.get("timeout_s", 1800))
    details = {"command": shown, "rater_version": version, "num_frames": int(oc.get("num_frames", 32))}
    log.info("VideoPhy2 %s: running the official rater: %s", task, shown)
    t0 = time.perf_counter()
    try:
        proc = subprocess.Popen(cmd, shell=isinstance(cmd, str), cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    except OSError as e:
        return not_rated(task, f"cannot start the VideoPhy2 rater: {e}", BACKEND, **details)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        _kill_group(proc)
        try:
            out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:   # a grandchild that left the group holds the pipes
            out, err = b"", b""
        details |= {"seconds": round(time.perf_counter() - t0, 2), "returncode": proc.returncode}
        return not_rated(task, f"the VideoPhy2 rater timed out after {timeout:g} s ({KEY}.timeout_s) and was "
                               f"killed; stderr: {tail(err, 800) or '(empty)'}", BACKEND, **details)
    details |= {"seconds": round(time.perf_counter() - t0, 2), "returncode": proc.returncode,
                "stdout_tail": tail(out, 600)}
    if proc.returncode != 0:
        return not_rated(task, f"the VideoPhy2 rater exited with status {proc.returncode}; stderr: "
                               f"{tail(err, 800) or '(empty)'}", BACKEND, **details)
    try:
        rating, cell, why = read_output_csv(out_csv, video)
    except Malformed as e:
        return not_rated(task, f"malformed rater output: {e}; stderr: {tail(err, 400) or '(empty)'}", BACKEND, **details)
    if rating is None:
        return not_rated(task, f"{why}; stdout: {tail(out, 400) or '(empty)'}", BACKEND, raw_scores=[cell], **details)
    return rated(task, [rating], mapping, BACKEND, True, raw_scores=[cell], **details)


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        proc.kill()


def rate(video: str, caption: str, tasks: list[str], oc: dict, mapping: str, log: logging.Logger) -> dict:
    """{task: score entry} for ``tasks`` from the official rater (one run per task)."""
    import tempfile

    video = str(Path(video).resolve())
    with tempfile.TemporaryDirectory(prefix="physgs-videophy2-") as work:
        return {t: run_task(t, video, caption, oc, mapping, work, log) for t in tasks}
