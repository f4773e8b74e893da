"""The `prior` backend: map a scene prompt and per-instance hints to knowledge-base materials.

Deterministic text matching, no weights.  Evidence for an instance is looked for in tiers,
the first tier with a match decides and its explanation is recorded:

1. an alias of a material in the instance hint (first one in the hint's main clause, i.e.
   before a relational word such as "on", "against", "in", "with"; else the first anywhere);
2. an alias in the instance name;
3. an alias in the clause of the scene prompt that mentions the instance name
   ("a rubber duck drops onto a stone": the clause of "duck" is "a rubber duck drops");
4. the same three places again with `descriptors`, the weak words ("wobbly", "bouncy");
5. materials the prompt names anywhere, in order of mention, preferring ones no other
   instance has taken yet (this is all an unmatched cluster label has);
6. prompt descriptors the same way;
7. `materials.default_material`.

"a rubber duck on a stone" with instances duck and stone gives duck -> rubber (tier 3) and
stone -> stone (tier 2).
"""
from __future__ import annotations

import hashlib
import re
from dataclasses import dataclass, field

from .. import materials_kb

# Words that end the clause describing one object ("a rubber duck | on | a stone").
RELATIONAL_WORDS = frozenset({
    "on", "onto", "upon", "atop", "against", "into", "in", "inside", "beside", "next", "near",
    "above", "below", "under", "beneath", "over", "with", "and", "behind", "from", "at", "to",
    "toward", "towards", "off", "across", "through", "between", "while", "then", "than",
    "where", "which", "that", "by", "until", "as",
})

_TOKEN = re.compile(r"[a-z0-9]+(?:['\-][a-z0-9]+)*")


@dataclass
class PriorMatch:
    """Outcome of matching one instance.

    Attributes:
        material: KB material name.
        tier: which evidence decided ("hint", "name", "prompt_clause", "hint_descriptor", ...,
            "prompt", "prompt_descriptor", "default").
        word: the alias or descriptor that matched (None for the default).
        reason: one human-readable sentence explaining the choice.
        candidates: other materials seen in the same tier, in order of mention.
        text_sha256: sha256 of the texts the matcher read (hint, name, prompt).
    """

    material: str
    tier: str
    word: str | None
    reason: str
    candidates: list[str] = field(default_factory=list)
    text_sha256: str = ""

    def to_dict(self) -> dict:
        return {"material": self.material, "tier": self.tier, "word": self.word, "reason": self.reason,
                "candidates": list(self.candidates), "text_sha256": self.text_sha256}


@dataclass(frozen=True)
class _Hit:
    pos: int            # token index where the phrase starts
    length: int         # number of tokens
    material: str
    word: str           # the alias/descriptor as written in the KB
    strong: bool        # alias (True) or descriptor (False)


def tokens(text: str | None) -> list[str]:
    """Lower-case word tokens (hyphenated words and apostrophes kept inside one token)."""
    return _TOKEN.findall((text or "").lower())


def _variants(tok: str) -> set[str]:
    """The token and its singular guesses ("stones" -> "stone", "berries" -> "berry")."""
    out = {tok}
    if len(tok) > 3 and tok.endswith("ies"):
        out.add(tok[:-3] + "y")
    if len(tok) > 3 and tok.endswith("es"):
        out.add(tok[:-2])
    if len(tok) > 2 and tok.endswith("s") and not tok.endswith("ss"):
        out.add(tok[:-1])
    return out


class Matcher:
    """Phrase matcher over the KB's aliases (strong) and descriptors (weak)."""

    def __init__(self, kb: dict | None = None, default_material: str = "jelly") -> None:
        self.kb = kb or materials_kb.load_kb()
        self.default_material = materials_kb.resolve_material_name(default_material, self.kb,
                                                                   "materials.default_material")
        self._phrases: dict[str, list[tuple[tuple[str, ...], str, str, bool]]] = {}
        for name, e in self.kb.items():
            for strong, words in ((True, [name] + e["aliases"]), (False, e["descriptors"])):
                for w in words:
                    toks = tuple(tokens(w.replace("_", " ")))
                    if toks:
                        self._phrases.setdefault(toks[0], []).append((toks, name, w, strong))
        for lst in self._phrases.values():   # longest first; aliases before descriptors
            lst.sort(key=lambda p: (-len(p[0]), not p[3]))

    # ------------------------------------------------------------------ scanning
    def hits(self, toks: list[str]) -> list[_Hit]:
        """Non-overlapping phrase matches, scanning left to right, longest phrase first."""
        out, i = [], 0
        while i < len(toks):
            hit = self._match_at(toks, i)
            if hit:
                out.append(hit)
                i += hit.length
            else:
                i += 1
        return out

    def _match_at(self, toks: list[str], i: int) -> _Hit | None:
        for first in _variants(toks[i]):
            for phrase, name, word, strong in self._phrases.get(first, ()):
                n = len(phrase)
                if i + n <= len(toks) and all(phrase[j] in _variants(toks[i + j]) for j in range(1, n)):
                    return _Hit(i, n, name, word, strong)
        return None

    # ------------------------------------------------------------------ single texts
    def first_in_text(self, text: str | None, strong: bool) -> tuple[_Hit | None, list[str]]:
        """First match (main clause first) and all materials seen, for aliases or descriptors."""
        toks = tokens(text)
        hits = [h for h in self.hits(toks) if h.strong == strong]
        if not hits:
            return None, []
        end = _main_clause_end(toks)
        main = [h for h in hits if h.pos < end]
        best = (main or hits)[0]
        return best, _unique(h.material for h in hits)

    def clause_of_name(self, prompt: str | None, name: str | None, strong: bool) -> tuple[_Hit | None, list[str]]:
        """First match inside the prompt clause that mentions ``name``."""
        ptoks, ntoks = tokens(prompt), tokens((name or "").replace("_", " "))
        if not ptoks or not ntoks:
            return None, []
        for start in range(len(ptoks) - len(ntoks) + 1):
            if all(ntoks[j] in _variants(ptoks[start + j]) for j in range(len(ntoks))):
                lo, hi = _clause_bounds(ptoks, start, start + len(ntoks))
                hits = [h for h in self.hits(ptoks[lo:hi]) if h.strong == strong]
                if hits:
                    return hits[0], _unique(h.material for h in hits)
        return None, []

    # ------------------------------------------------------------------ instances
    def match_named(self, name: str | None, hint: str | None, prompt: str | None) -> PriorMatch | None:
        """Tiers 1-4 for an instance with a scene-config entry; None if nothing matched."""
        digest = _digest(hint, name, prompt)
        for strong in (True, False):
            suffix = "" if strong else "_descriptor"
            kind = "alias" if strong else "descriptor"
            hit, cands = self.first_in_text(hint, strong)
            if hit:
                return PriorMatch(hit.material, "hint" + suffix, hit.word,
                                  f"{kind} '{hit.word}' in the instance hint {hint!r}", cands, digest)
            hit, cands = self.first_in_text((name or "").replace("_", " "), strong)
            if hit:
                return PriorMatch(hit.material, "name" + suffix, hit.word,
                                  f"{kind} '{hit.word}' in the instance name {name!r}", cands, digest)
            hit, cands = self.clause_of_name(prompt, name, strong)
            if hit:
                return PriorMatch(hit.material, "prompt_clause" + suffix, hit.word,
                                  f"{kind} '{hit.word}' next to '{name}' in the scene prompt {prompt!r}", cands, digest)
        return None

    def prompt_materials(self, prompt: str | None, strong: bool) -> list[tuple[str, str]]:
        """(material, word) pairs named in the prompt, main clause first, then in order of mention."""
        toks = tokens(prompt)
        hits = [h for h in self.hits(toks) if h.strong == strong]
        end = _main_clause_end(toks)
        ordered = [h for h in hits if h.pos < end] + [h for h in hits if h.pos >= end]
        seen, out = set(), []
        for h in ordered:
            if h.material not in seen:
                seen.add(h.material)
                out.append((h.material, h.word))
        return out


def match_scene(prompt: str | None, instances: list[dict | None], kb: dict | None = None,
                default_material: str = "jelly") -> list[PriorMatch]:
    """One :class:`PriorMatch` per instance (in the given order, e.g. by cluster label).

    Args:
        prompt: the scene prompt.
        instances: per instance ``{"name": ..., "hint": ...}`` (the scene-config entry) or
            None for a cluster label that matched no config entry.
        kb: knowledge base (default: the packaged one).
        default_material: used when nothing in the texts names a material.
    """
    m = Matcher(kb, default_material)
    out: list[PriorMatch | None] = []
    for inst in instances:
        out.append(m.match_named(inst.get("name"), inst.get("hint"), prompt) if inst else None)
    taken = {p.material for p in out if p is not None}
    for strong, tier in ((True, "prompt"), (False, "prompt_descriptor")):
        pool = m.prompt_materials(prompt, strong)
        if not pool:
            continue
        fresh = [p for p in pool if p[0] not in taken] or pool
        k = 0
        for i, inst in enumerate(instances):
            if out[i] is not None:
                continue
            mat, word = fresh[k % len(fresh)]
            k += 1
            kind = "alias" if strong else "descriptor"
            who = f"instance {inst.get('name')!r}" if inst else "this unmatched cluster"
            why = (f"{kind} '{word}' in the scene prompt {prompt!r} (nothing in the hint or name of {who}; "
                   f"prompt materials in order: {', '.join(p[0] for p in pool)}; preferring ones no other instance took)")
            out[i] = PriorMatch(mat, tier, word, why, [p[0] for p in pool],
                                _digest(inst.get("hint") if inst else None, inst.get("name") if inst else None, prompt))
    for i, inst in enumerate(instances):
        if out[i] is None:
            out[i] = PriorMatch(m.default_material, "default", None,
                                f"no material word in the hint, name or prompt; materials.default_material = "
                                f"'{m.default_material}'", [],
                                _digest(inst.get("hint") if inst else None, inst.get("name") if inst else None, prompt))
    return [p for p in out if p is not None]


def _main_clause_end(toks: list[str]) -> int:
    """Index of the first relational word after the first content word (or len(toks))."""
    for i, t in enumerate(toks):
        if i > 0 and t in RELATIONAL_WORDS:
            return i
    return len(toks)


def _clause_bounds(toks: list[str], start: int, stop: int) -> tuple[int, int]:
    lo = start
    while lo > 0 and toks[lo - 1] not in RELATIONAL_WORDS:
        lo -= 1
    hi = stop
    while hi < len(toks) and toks[hi] not in RELATIONAL_WORDS:
        hi += 1
    return lo, hi


def _unique(items) -> list[str]:
    seen, out = set(), []
    for x in items:
        if x not in seen:
            seen.add(x)
            out.append(x)
    return out


def _digest(hint: str | None, name: str | None, prompt: str | None) -> str:
    text = f"hint={hint or ''}\nname={name or ''}\nprompt={prompt or ''}"
    return hashlib.sha256(text.encode()).hexdigest()
