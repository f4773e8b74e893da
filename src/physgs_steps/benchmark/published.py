"""The paper's published numbers (FastPhysGS, fastphysgs.tex), shown beside ours and always
marked "published, RTX A6000": "All experiments are conducted on a single NVIDIA RTX A6000
GPU with 48 GB memory, with each method simulating and rendering 150 frames" (Sec. 5.1).
Nothing here is measured by this project.
"""
from __future__ import annotations

SOURCE = "published, RTX A6000"

# Table 1 (tab:com): method, venue, automatic parameters, CS, AS, SA, PC, memory (GB), time (min)
COMPARISON = [
    {"method": "CogVideoX1.5-5B", "venue": "ICLR'25", "auto_params": None, "CS": 0.269, "AS": 4.04, "SA": 0.44,
     "PC": 0.21, "memory_gb": 33, "minutes": 24},
    {"method": "Veo-3.1", "venue": "Google'25", "auto_params": None, "CS": 0.291, "AS": 4.90, "SA": 0.81, "PC": 0.49,
     "memory_gb": None, "minutes": None},
    {"method": "PhysGaussian", "venue": "CVPR'24", "auto_params": False, "CS": 0.267, "AS": 4.06, "SA": 0.69,
     "PC": 0.55, "memory_gb": 12, "minutes": 2},
    {"method": "Physics3D", "venue": "arXiv'24", "auto_params": True, "CS": 0.275, "AS": 4.48, "SA": 0.81, "PC": 0.53,
     "memory_gb": 30, "minutes": 90},
    {"method": "DreamPhysics", "venue": "AAAI'25", "auto_params": True, "CS": 0.279, "AS": 4.38, "SA": 0.75,
     "PC": 0.51, "memory_gb": 35, "minutes": 90},
    {"method": "OmniPhysGS", "venue": "ICLR'25", "auto_params": True, "CS": 0.265, "AS": 4.35, "SA": 0.63, "PC": 0.45,
     "memory_gb": 40, "minutes": 120},
    {"method": "FastPhysGS (paper)", "venue": "-", "auto_params": True, "CS": 0.292, "AS": 4.71, "SA": 0.87,
     "PC": 0.61, "memory_gb": 7, "minutes": 1},
]

# Table 4 (tab:aba): CS, AS, SA, PC, memory (GB), time (min)
ABLATIONS = [
    {"method": "w/o IPF", "ablation": "no_ipf", "CS": 0.263, "AS": 4.26, "SA": 0.60, "PC": 0.44, "memory_gb": 5,
     "minutes": 0.8},
    {"method": "w/o MCIS", "ablation": "no_mcis", "CS": 0.285, "AS": 4.31, "SA": 0.72, "PC": 0.52, "memory_gb": 7,
     "minutes": 1},
    {"method": "w/o BGDO", "ablation": "no_bgdo", "CS": 0.217, "AS": 3.34, "SA": 0.57, "PC": 0.36, "memory_gb": 7,
     "minutes": 0.5},
    {"method": "Ours (full)", "ablation": None, "CS": 0.292, "AS": 4.71, "SA": 0.87, "PC": 0.61, "memory_gb": 7,
     "minutes": 1},
]

# Table 3 (tab:timememory), averaged over the paper's data set. "<1 s" is kept as text.
STAGES = {
    "IPF": {"time": "22 s", "memory": "1.6 GB"},
    "BGDO forward": {"time": "39 s", "memory": "7 GB"},
    "BGDO backward": {"time": "<1 s", "memory": "7 GB"},
    "full": {"time": "1 min", "memory": "7 GB"},
}

# Sec. 5.3: the corrupted starts of the robustness experiment and the 60-run figure.
ROBUSTNESS_E0 = (3e10, 3e8, 30.0)
STRESS_RUNS = 60
