"""The science: one module per stage, pure functions on numpy arrays, and the executors.

Where a part of the seeds (``../shared/seeds``) lives, and its stage id:

- NIST §2-3.1 bins, select/reject, plane fits (§7): ``bins``; stage ``ground.nist``
- NIST §2, §3.1.1 TIN masking: ``ground/masking`` (on the TIN tools of ``ground/tin``)
- NIST §3.1-3.3 meshing, screening, mowing, the pass schedule of §6.1: ``ground/nist``;
  ground growth, supported points and raised segments: ``ground/growth``,
  ``ground/support``, ``ground/raised``
- NIST §7 concentric grid for ground-based scans: ``ground/concentric``
- NIST §4 tree and bush bins, coverage: ``vegetation``; stage ``vegetation``
- NIST §5 slope, pitch and roll, roughness: ``terrain`` (``dem`` grids the DTM/DSM);
  stage ``terrain``
- Pack: steepness test and rotated runs OR'ed: ``ground/rotation``; stages
  ``ground.steep``, ``ground.rotation``
- Pack (after Axelsson): progressive TIN densification: ``ground/ptd``; stage ``ground.ptd``
- Tuley: interest box, saliency, triggers, marking: ``mixed`` (box geometry in
  ``mixed_box``); stage ``mixed``
- Sjövall §1.4 categories: ``categories``; stage ``categories``
- Sjövall §2-3 and Appendix A filters: ``features/`` (``language`` parses, ``search``
  finds segments, ``connect`` joins them, ``objects`` measures, ``filters/*.flt``
  the built-in filters); stage ``features``

Besides: ``ground/lowpoints`` (isolated low points, ``ground.lowpoints``),
``surface`` (the ground surface on the TIN of ``ground/tin``), ``scan_geometry`` (angular
steps, range noise and footprint of ground-based scans). ``block`` runs the block
steps of ``steps`` on one block with the parameter models the jobs room
builds; ``registry`` holds the stages and steps; ``executors`` the process
pool and Dask.
"""
