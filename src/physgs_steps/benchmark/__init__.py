"""The benchmark: the paper's tables and figures regenerated as cached workflow targets.

``snakemake --cores all benchmark`` builds ``results/benchmark/<scale>/REPORT.md`` (with
``tables/*.csv`` and ``figures/*.png``) from ordinary runs of the workflow's rules:

* :mod:`.spec` - what runs: the scale's scenes and sizes, the variants (physgs, the
  PhysGaussian-style baseline, the ablations, the BGDO robustness starts) as config overlays,
  their plans under ``results/benchmark/<scale>/runs/<scene>[/variants/<name>]``, and the
  stress-vs-E runs;
* :mod:`.stress` - the ``bench_stress`` stage: one forward simulation and one BGDO step from a
  given initial E, with the per-particle stress of its key frames;
* :mod:`.readers` - small adapters that read the runs' outputs (metrics.json scores,
  final.h5 stats, params.json BGDO history, fill_report.json, Snakemake's benchmark files
  and stage summaries), tolerant of missing keys (a value that is missing is ``None`` with
  the reason), so that changes of those formats touch one place;
* :mod:`.physical` - weight-free physical figures read from final.h5 (ground and
  inter-instance penetration, volume change, NaN, domain);
* :mod:`.tables` - the rows of every table; :mod:`.figures` - stress-vs-E plot and the small
  contact sheets; :mod:`.published` - the paper's numbers; :mod:`.report` - the
  ``benchmark_stages`` and ``benchmark_report`` stages that write the report.
"""
