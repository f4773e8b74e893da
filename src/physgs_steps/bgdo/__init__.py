"""BGDO, Bidirectional Graph Decoupling Optimisation of Young's modulus (FastPhysGS Sec. 4.2,
Appendix B.1-B.5, Algorithm 1): the torch pseudo step, the signals, the update and the stage.

Modules: :mod:`.torch_step` (the torch mirror of one MPM substep), :mod:`.update` (signals,
unstable-run handling and the update rule), :mod:`.stage` (the ``bgdo_update`` stage, key-frame
files).

Iterations (the workflow's DAG)::

    params_0 -> forward_sim -> forward.h5 (key frames) -> bgdo_update -> params_1 -> ... -> params_N -> final_sim

N = ``bgdo.iterations`` (default 2; 0 is the "without BGDO" ablation and runs no forward
simulation). ``forward_sim`` (physgs_steps.simulate, Taichi, no gradients) stores only the key
frames ``round(f (T - 1))``, f in ``bgdo.key_frames`` (default the paper's f_0, f_t, f_n), with
x, v, C, F of every particle. :func:`run` is the stage ``bgdo_update``.

Pseudo step
-----------
:func:`pseudo_step` is one MLS-MPM substep in torch from a stored state, exactly the step of
docs/CONTRACTS.md: the Kirchhoff stress of each instance's elasticity model
(:func:`kirchhoff`), P2G over the 27 offsets with ``index_add`` into the grid nodes the
particles touch, grid update with gravity and the domain walls (slip/sticky, 3 nodes), G2P,
then each instance's plasticity return map (:func:`return_map`). ``log E`` per instance is the
leaf; every operation is differentiable (the 3x3 SVD has a closed-form backward that stays
finite for repeated singular values, e.g. F = I). Like the Taichi solver, the stencil base is
clamped to [0, G - 3]. The pseudo step has no colliders, ground plane, damping or particle
actions (CONTRACTS.md: the Taichi solver applies those). tests/test_bgdo.py checks it against
an independent NumPy implementation (float64, 1e-8) and against one Taichi substep for every
elasticity x plasticity pair (float32 tolerance). Only one key frame and one step's graph are
in memory at a time (:func:`iter_keyframes`), so memory does not grow with the number of key
frames (measured on CPU: +91 MiB for the 13.6k-particle bear, +790 MiB for 200k particles, the
same with 3 or 9 key frames, about 4 KiB per particle); the stage records peak RSS and, on
CUDA, torch's peak allocation.

Signals (per instance k, key frame i, particle p of k)
------------------------------------------------------
    g_p     = d||tau_p||_F / d log E_k          by autograd through the stress (Pa)
    g~_i    = mean_p log(1 + |g_p| / p_ref_k)   compressed per particle, then averaged
    delta_i = mean_p d(F'_p)                    F' after the step and the return map

tau is linear in (mu, lambda), hence in E, for all five models, so g_p = ||tau_p||_F exactly
(a check in the tests): the "stress gradient" is the stress magnitude.

Update
------
    eta  = min(1, 0.1 log(1 + E_k / p_ref_k))                       (bgdo.eta_rule paper)
    G    = eta mean_i g~_i - (1 - eta) mean_{i > 0} log(delta_i / delta_target_k)
    log E_k <- log E_k - clip(G, -max_step, max_step),  never raised above the solver ceiling

This is ``variant: algorithm1`` (default) with ``deformation_signal: log_ratio`` (default).
With ``deformation_signal: difference`` it is Appendix B.5's update and Algorithm 1 literally:

    G    = sum_i w_i [eta g~_i - (1 - eta)(delta_i - delta_target_k) / s_delta] / sum_i w_i

Why the log ratio: for a linear material under a fixed load the deformation is proportional to
1 / E, so d log(delta) / d log E = -1 and log(delta / delta_target) is exactly the Newton step
of log E onto the target; (1 - eta) damps it. The literal difference is bounded below (-1 in
units of the target: a frame that does not deform at all asks for a decrease of at most
1 - eta) and grows linearly above, so its step sizes depend on s_delta and max_step rather than
on how far E is from its target: measured with the first implementation (difference, one
delta_target 0.1 for all materials), a collapse raised E by the whole max_step and a key frame
deforming 2x the target lowered it as much as one deforming 20x. The log ratio is undefined
for the rest state (frame 0, F = I, delta = 0), which carries no deformation information: the
deformation term averages the key frames after frame 0, the stress term all key frames.

Per-material target: ``delta_target: null`` (default) gives each instance delta_target_k =
rho_k g h_ref / E_ref_k (h_ref = ``reference_height``, 0.3 m): the strain its own weight causes
in a 0.3 m object of its material at the material's reference modulus (jelly 0.044, bread
0.010, rubber 0.010, foam 0.0032, stone 3.4e-4). The paper's single target 0.1
(``delta_target: 0.1``) pulls every material to 10% stretch, so a stone, a metal can or a
wooden basket lands at jelly stiffness and a light material (bread, 250 kg/m^3) far below its
band (measured with the first implementation: the stone of duck_stone 3e8 -> 3e5 -> 1.4e5 Pa,
band 5e6-1e8; bread from any start 4e3 Pa, band 1e4-5e5). A first per-material version with
one characteristic stress for every material (7 kPa / E_ref) fixed the stiff materials but
still left bread (4e3 Pa) and the foam mat (267 Pa) below their bands: the load scales with the
density, so the target has to as well.

The main text (Sec. 4.2, Eqs. 6-8) reads differently; ``variant: main_text`` implements it:

    g_tau = mean_i mean_p |g_p| / p_ref_k,   g = log(1 + g_tau),   d_F = mean_i delta_i / s_delta
    G     = eta g - (1 - eta) d_F

The differences: (1) where the compression sits: Algorithm 1 compresses each particle's
gradient and then averages (the appendix: the log "reduces the influence of extreme outliers
during spatial averaging across particles or temporal averaging across key frames"); the main
text averages over the three key frames first and compresses once. With outliers (a few
particles near inversion) the main-text signal follows the outliers, Algorithm 1's the typical
particle. (2) The deformation term: Algorithm 1 uses delta - delta_target (a key frame
deforming less than the target pushes E down, more pushes it up), the main text the plain mean
d_F, which always pushes E up, so E only falls when the stress term outweighs it. Two smaller
differences are not options: the main text differentiates with respect to E and writes the
key-frame F_i, the appendix with respect to log E and the stepped F'; both variants here use
d/dlog E (log E is the leaf; d||tau||/dE = ||tau||/E would not depend on E at all) and F'.

Units: the reference scale
--------------------------
Read literally in SI units (``scaling: si``), eta = min(1, 0.1 log(1 + E/Pa)) is 1 for every
E above e^10 - 1 = 22 kPa, so the deformation term vanishes for all solid materials and G =
mean log(1 + ||tau||/Pa) > 0: log E only decreases, by ~5.6 per iteration at the bear's
stresses of a few kPa (3e8 -> 3e5 -> 1.1e3 Pa, a collapse), and below 22 kPa the unscaled
deformation term is too weak to lift a collapsed object (30 -> 44 -> 63 Pa); see the
benchmark's robustness table with ``--config bgdo='{scaling: si}'``. The paper's E values are in a simulator's
normalised units. ``scaling: reference`` (default) keeps the formulas and makes their
arguments dimensionless:

* E and the stress gradient in units of a reference pressure ``p_ref = reference_strain *
  E_ref`` (reference_strain 0.1), the Kirchhoff stress of the material's reference modulus at
  10% strain (||tau|| ~ E ||eps|| for small strain). E_ref is the geometric mean of the
  material's ``E_range`` in the knowledge base (data/materials.yaml; jelly: sqrt(1e4 * 5e5) =
  7.1e4 Pa, so p_ref = 7.1 kPa), or ``bgdo.reference_modulus`` for a material not in it;
  ``bgdo.reference_pressure`` fixes one p_ref for all instances. Then eta = 0.24 at E = E_ref
  for every material, 0.09 at the jelly band's lower end, 0.43 at its upper end and 1 above
  E = 22000 p_ref: an over-stiff E lets the stress term dominate (E decreases), an over-soft E
  lets the deformation term dominate (E increases), and in the band both are O(1).
* The deformation relative to its target (log_ratio), or in units of ``s_delta =
  delta_target`` (``bgdo.deformation_scale``, deformation_signal difference).
* ``max_step`` (default ln 10000) bounds |G| per iteration (a trust region for the signals).

Unstable forward runs
---------------------
forward_sim stops at the first unstable frame and stores the last stable state in place of
the key frames it could not reach (attribute ``substitute_for``). :func:`unstable_run_info`
decides per instance: "exploded" when its CFL number (wave speed x dt / dx of the failing
frame) exceeded ``bgdo.cfl_limit`` (1): it was too stiff for the substep cap; "broken" when the
failure message names it (collapse J < j_min, tearing, leaving the domain) without a CFL
violation: it could not carry its load. A failed run measures nothing for the key frames it
did not reach, so ``failure_rule: static_load`` (default) uses two facts that do not need
them (:func:`assemble_frames`, :func:`bgdo_update`):

* the solver ceiling E_cap (:func:`solver_ceiling`): the stiffest modulus the configured
  substep cap integrates at its CFL number. An exploded instance goes to min(E_cap,
  rho |g| H / delta_target), the ceiling or the modulus at which its own weight strains it by
  the target (:func:`static_stress`: rho |g| H is the static stress at the base of an
  instance of height H). No update raises E above the ceiling (``ceiling: true``), so the
  final simulation does not explode either.
* the static strain rho |g| H / E: a broken instance's missing key frames count with the
  deformation max(collapse deformation sqrt(3)(1 - j_min^(1/3)) = 1.09, static strain), and an
  instance the failure did not involve but whose static strain exceeds the collapse
  deformation (it cannot carry its own weight) is broken too. An uninvolved instance that can
  carry its weight uses the key frames that were stored, and keeps its E if none after frame 0
  was.

``failure_rule: max_step`` is the first implementation: exploded key frames count as an
infinite stress signal (the paper's log(1 + |g|) of a diverged stress), so G = max_step;
broken ones with the collapse deformation only; uninvolved instances keep E. Without any
failure handling the over-soft case goes the wrong way: the bear at 30 Pa collapses at impact,
its last stable frame (still falling) shows delta = 0.04 and BGDO would lower E (30 -> 14 ->
6.5 Pa).

Robustness (measured with the former script benchmarks/bgdo_robustness.py on an H200 for every
built-in scene at the main job's size, n_grid 32, 150 frames; the benchmark's section 4 now
regenerates it: ``snakemake benchmark``, README "Regenerating the benchmark"). E0 -> E1 -> E2 in Pa;
every final simulation is stable, and without BGDO every corrupted start is unstable. c: held
at the solver ceiling E_cap; x: outside the band.

    instance (material) band      from 3e10 (3e8: same)    from 30                  from the KB E
    bear (jelly) [1e4, 5e5]       1.23e5 -> 1.10e5         1.22e5 -> 1.10e5         5e4 -> 7.2e4 -> 8.4e4
    bear_can: bear (jelly)        1.11e5 -> 1.06e5         1.11e5 -> 1.10e5         5e4 -> 8.4e4 -> 9.4e4
    bear_can: can (metal) [5e6, 1e8] 1.37e7 -> 5.13e7 c    3e5 -> 1.54e7            2e7 -> 5.13e7 c -> 5.13e7 c
    duck (rubber) [1e5, 1e6]      2.52e5 -> 4.26e5         2.52e5 -> 5.59e5         5e5 -> 6.2e5 -> 7.1e5
    stone (stone) [5e6, 1e8]      1.43e7 -> 1.90e7 c       3e5 -> 1.90e7 c          2e7 -> 2e7 -> 2e7
    ficus (plant) [5e4, 5e6]      4.57e6 c -> 4.16e5       9.2e3 -> 4.0e4 x         3e5 -> 3.7e5 -> 2.7e5
    mat (foam) [1e4, 3e5]         2.23e3 -> 1.16e5         1.17e4 -> 1.64e5         3e4 -> 2.0e5 -> 4.0e5 x
    basket (wood) [2e6, 1e8]      3.92e6 c -> 3.92e6 c     3e5 -> 3.92e6 c          1e7 -> 1e7 -> 1e7
    bread (bread) [1e4, 5e5]      4.17e4 -> 6.27e4         4.16e4 -> 6.26e4         5e4 -> 6.8e4 -> 7.8e4

The 300k-gaussian bear at n_grid 64 (360,603 particles), which collapses at impact with its
knowledge-base E: 5e4 -> 6.5e5 -> 2.9e5 and 30 -> 1.2e5 -> 1.1e5, final runs stable (the first
implementation oscillated 5e4 -> 1.6e7 -> 1.6e4 and its final run collapsed).

Limitations (measured: the benchmark's robustness table and stress-vs-E figure)
-------------------------------------------------------------------------------------
* BGDO does not discover E from nothing: its fixed point is where the key-frame stretch
  matches delta_target, so the target decides where it lands. With the per-material target an
  object loaded by its own weight lands near E_ref x H / 0.4 m; an object loaded by something
  else lands where that load strains it like its own weight would strain a 0.3 m object (the
  foam mat under the basket: 4e5 Pa from its KB 3e4, above its band), and an instance with no
  gravity (the ficus in wind) has no static estimate, so from 30 Pa it needs a third iteration.
* A collapse is a yes/no signal: the collapsed key frames count with at least the collapse
  deformation, so a slightly too soft E overshoots (300k bear at grid 64: 5e4 -> 6.5e5) and
  the next iteration comes back down.
* The ceiling depends on the solver settings: stiff materials (stone, metal, wood) end at E_cap,
  which falls 4x per doubling of n_grid (stone: 1.9e7 Pa at grid 32, 4.8e6 at 64, below its
  band); raise sim.max_substeps for them.
* The mean stretch over an instance dilutes local deformation (a mat deformed only under the
  basket, a plant bent at its stems).

Deformation measure
-------------------
``deformation_measure: stretch`` (default) uses d(F') = ||F' - R'||_F = ||sigma' - 1||, the
rotation-free part; ``frobenius`` the paper's ||F' - I||_F. Appendix B.3 treats ||F' - I|| as a
strain proxy "because rotations are close to identity", true for one substep's increment but
not for the accumulated elastic F: the built-in bear tips over when it lands, and at its
knowledge-base E = 5e4 Pa the key frames have mean ||F - I|| = 1.74 with ||F - R|| = 0.08, which
the literal measure reads as a material 17 times softer than the target.

Plausible band
--------------
The band of a material is its ``E_range`` in the knowledge base: simulation-effective moduli
(not handbook values) for a 0.5 m tabletop object at n_grid 32-64 and 30 fps. For jelly,
[1e4, 5e5] Pa. It is right for this simulator because it contains gelatin's measured 1-100 kPa
and matches what the bear does (the benchmark's stress-vs-E figure, 60 runs): below ~1.2e4 Pa it
collapses at impact (J < sim.stability.j_min), from ~1.7e4 Pa it lands and wobbles, and
towards 5e5 Pa the key-frame stretch falls below 1 % (it barely deforms) while the explicit
step needs ~54 substeps per frame at n_grid 32. Stiff materials' bands (stone, metal, wood
from 2e6-5e6 Pa up) are where they barely deform at all; their upper part is beyond the solver
ceiling at the default substep cap.
"""
from __future__ import annotations

from .torch_step import (  # noqa: F401
    ELASTICITY, PLASTICITY, SIG_FLOOR, J_FLOOR, SVD_GAP, canonical_elasticity, canonical_plasticity,
    svd3, lame, kirchhoff, PlasticParams, PLASTIC_KEYS, return_map, fracture_step, degrade, InstanceTable, instance_table,
    log_E_from_instances, GridSpec, particle_stress, plastic_projection, mpm_step, pseudo_step,
)
from .update import (  # noqa: F401
    G_REF, DELTA_FLOOR, Scales, reference_scales, solver_ceiling, static_stress, frame_signals,
    bgdo_signals, wave_speeds, failing_instances, unstable_run_info, assemble_frames, eta_value, bgdo_update,
)
from .stage import (  # noqa: F401
    key_frame_indices, read_keyframes_meta, iter_keyframes, resolve_device, grid_from_config, run,
)
