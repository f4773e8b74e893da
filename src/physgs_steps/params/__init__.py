"""Material parameters per instance (stage `vlm_params`).

Backends: :mod:`.prior` (knowledge-base text matching, default), :mod:`.qwen3vl` (local
Qwen3-VL through transformers) and :mod:`.openai_backend` (OpenAI-compatible endpoint).
:mod:`.prompt` builds the question and the retry loop, :mod:`.validate` checks pins and
answers, :mod:`.views` renders an instance for the VLMs, :mod:`.stage` is the stage entry
``run(inputs, outputs, cfg, log)`` plus ``fully_pinned`` / ``pinned_params``.
"""
