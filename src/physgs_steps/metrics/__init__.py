"""The metrics stage and its parts (every module imports torch/transformers only when used).

| module | what |
|---|---|
| :mod:`.stage` | the stage: ``run(inputs, outputs, cfg, log)`` -> metrics.json |
| :mod:`.scores` | the one shape of every video score (value or null + reason, backend, ...) |
| :mod:`.video` | decoding the video once, keeping only the sampled frames |
| :mod:`.clip_aesthetic` | CLIP score (CS) and LAION aesthetic score (AS), architecture checks |
| :mod:`.videophy2` | VideoPhy2 SA / PC: the rater's questions, answer parsing, 1-5 -> 0-1 mapping, backend choice |
| :mod:`.videophy2_official` | the official VideoPhy-2 auto-rater as a subprocess in its own environment |
| :mod:`.videophy2_inprocess` | a stand-in rater: the same questions asked of a local Qwen3-VL |
| :mod:`.physical` | plausibility figures of final.h5 (``physical_figures``) |
"""
from .clip_aesthetic import aesthetic_scores, image_embeddings, load_aesthetic, load_clip, text_embedding
from .physical import physical_figures
from .stage import run
from .video import read_frames, read_video_frames, sample_indices

__all__ = ["run", "physical_figures", "read_frames", "read_video_frames", "sample_indices", "load_clip",
           "image_embeddings", "text_embedding", "load_aesthetic", "aesthetic_scores"]
