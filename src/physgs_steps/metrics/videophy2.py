"""VideoPhy2's semantic adherence (SA) and physical commonsense (PC): protocol and backends.

The VideoPhy-2 auto-rater (``videophysics/videophy_2_auto``, mPLUG-Owl-Video, about 7B, MIT;
``VIDEOPHY2/inference.py`` in the VideoPhy repository) rates a video 1-5 for a task:

* ``sa``: does the video match its caption (5 = perfect match, 1 = no relevance);
* ``pc``: does the video follow the physical laws (5 = full compliance, 1 = significant
  violations); the caption is not shown.

It samples 32 frames (the middle of 32 equal segments), decodes greedily and writes an
integer 0-5 into a ``score`` column (0 is what it writes when it cannot read its model's
answer). The paper reports SA and PC on 0-1 without saying how; ``metrics.videophy2.mapping``
chooses (README, "Where the paper is vague"):

* ``linear`` (default): (rating - 1) / 4, so 1 -> 0, 3 -> 0.5, 5 -> 1;
* ``threshold``: 1 when rating >= 4, else 0 (VideoPhy-2's own cut for "high" SA / PC; its
  mean over videos is the fraction of such videos).

Both mapped values and the raw ratings are recorded. Backends (``metrics.videophy2.backend``):

* ``official`` (:mod:`.videophy2_official`): the released rater in its own environment, run
  as a subprocess; the paper's metric.
* ``inprocess`` (:mod:`.videophy2_inprocess`): the same questions and 1-5 scale asked of a
  local Qwen3-VL through transformers; a stand-in, never the paper's metric
  (``paper_metric: false`` and a ``label`` saying so).
* ``auto``: ``official`` when configured, else ``inprocess`` when configured, else none; a
  failing rater is never replaced by the other one.
"""
from __future__ import annotations

import re

from ..errors import ConfigError
from .scores import measured, unavailable

TASKS = ("sa", "pc")
KEYS = {"sa": "semantic_adherence", "pc": "physical_commonsense"}
# The questions the VideoPhy-2 rater is asked (its templates in VIDEOPHY2/template.py), without
# the mPLUG-Owl conversation wrapper: a chat template supplies the roles.
QUESTIONS = {
    "sa": ('Does this video match the description: "{caption}"? Please rate the video on a scale from 1 to 5, '
           "where 5 indicates a perfect match and 1 indicates no relevance."),
    "pc": ("Does this video adhere to the physical laws? Rate the video on a scale from 1 to 5, "
           "where 5 means full compliance and 1 means significant violations."),
}
MAPPINGS = {
    "linear": "(rating - 1) / 4",
    "threshold": "1 if rating >= 4 else 0 (VideoPhy-2's 'high' cut)",
}
BACKENDS = {"official": "videophy2_official", "inprocess": "videophy2_inprocess"}
INPROCESS_LABEL = ("NOT the paper's metric: VideoPhy2's questions and 1-5 scale asked of a general video-language "
                   "model in-process, not of the VideoPhy-2 auto-rater")
_NUMBER = re.compile(r"(?<![\w.])(\d+(?:\.\d+)?|zero|one|two|three|four|five|six|seven|eight|nine|ten)(?![\w])(?!\.\d)",
                     re.IGNORECASE)
_WORDS = {w: i for i, w in enumerate(["zero", "one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten"])}


def map_rating(rating: int, mapping: str) -> float:
    """A 1-5 rating on 0-1 with ``mapping`` (``linear`` or ``threshold``)."""
    if not 1 <= rating <= 5:
        raise ValueError(f"a VideoPhy2 rating is 1-5, got {rating}")
    if mapping == "linear":
        return (rating - 1) / 4.0
    if mapping == "threshold":
        return 1.0 if rating >= 4 else 0.0
    raise ValueError(f"unknown mapping {mapping!r}; choose from {sorted(MAPPINGS)}")


def parse_rating(answer: str) -> tuple[int | None, str | None]:
    """(rating 1-5, None) from a model's answer, or (None, why not).

    The first number in the answer (digits or a word, e.g. "4", "Rating: 4/5", "four") is the
    rating; it must be a whole number from 1 to 5.
    """
    m = _NUMBER.search(answer or "")
    if m is None:
        return None, f"no rating in the answer {_quote(answer)}"
    tok = m.group(1).lower()
    num = float(_WORDS[tok]) if tok in _WORDS else float(tok)
    if num != int(num) or not 1 <= num <= 5:
        return None, f"the first number in the answer {_quote(answer)} is {m.group(1)}, not a rating from 1 to 5"
    return int(num), None


def rated(task: str, ratings: list[int], mapping: str, backend: str, paper_metric: bool, **details) -> dict:
    """The score entry of ``task`` from raw 1-5 ratings (one per rated video): mean mapped value."""
    per_mapping = {m: sum(map_rating(r, m) for r in ratings) / len(ratings) for m in MAPPINGS}
    return measured(KEYS[task], per_mapping[mapping], backend, paper_metric, task=task, ratings=list(ratings),
                    mapping={"name": mapping, "formula": MAPPINGS[mapping]}, value_by_mapping=per_mapping,
                    rating_scale="1-5 (5 best)", **details)


def not_rated(task: str, reason: str, backend: str | None = None, **details) -> dict:
    return unavailable(KEYS[task], reason, backend=backend, task=task, **details)


def select_backend(vc: dict) -> str:
    """``official``, ``inprocess``, ``none`` (switched off) or ``unconfigured`` (auto, nothing set)
    for the validated ``metrics.videophy2`` section.

    Raises:
        ConfigError when the section is inconsistent (checked before any work is done).
    """
    from . import videophy2_official as official

    backend = vc.get("backend", "auto")
    if backend not in ("auto", "official", "inprocess", "none"):
        raise ConfigError("metrics.videophy2.backend", f"must be auto, official, inprocess or none, got {backend!r}")
    mapping = vc.get("mapping", "linear")
    if mapping not in MAPPINGS:
        raise ConfigError("metrics.videophy2.mapping", f"must be one of {sorted(MAPPINGS)}, got {mapping!r}")
    tasks = vc.get("tasks", list(TASKS))
    bad = [t for t in tasks if t not in TASKS]
    if bad:
        raise ConfigError("metrics.videophy2.tasks", f"unknown task(s) {bad}; tasks are {list(TASKS)}")
    oc = vc.get("official") or {}
    if official.configured(oc):
        official.validate(oc)
    if backend != "auto":
        return backend
    if official.configured(oc):
        return "official"
    if (vc.get("inprocess") or {}).get("model_path"):
        return "inprocess"
    return "unconfigured"


def not_configured_reason(backend: str) -> str:
    """Why SA/PC are null when ``select_backend`` gave ``none`` or ``unconfigured``."""
    if backend == "none":
        return "metrics.videophy2.backend is none (VideoPhy2 is switched off)"
    return ("no VideoPhy2 rater configured: set metrics.videophy2.official.command (or .python, .repo and "
            ".checkpoint) to run the paper's VideoPhy-2 auto-rater, or metrics.videophy2.inprocess.model_path "
            "for an in-process stand-in that is not the paper's metric (README, 'Video metrics')")


def _quote(s: str | None, n: int = 200) -> str:
    s = "" if s is None else str(s)
    return repr(s if len(s) <= n else s[:n] + "...")
