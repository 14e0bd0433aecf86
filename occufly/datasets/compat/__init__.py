"""Dataset classes that plug an SSCBench-layout export into SSC codebases with configuration
changes (or, where a codebase cannot take a dataset from its configuration, a documented
two-edit patch: the DataModule's dataset import and the training script's literals). One
module per codebase, each written against that codebase's sample contract at a named
commit (docs/ssc-porting.md; tests/test_ssc_compat.py checks the contracts without the
codebases):

- :mod:`occufly.datasets.compat.symphonies` -- hustvl/Symphonies 4ca4ff2 (``OccuFlyKITTI360``
  + the Hydra callback ``Register``);
- :mod:`occufly.datasets.compat.monoscene` -- astra-vision/MonoScene f52bbb1
  (``KittiDataset``) and ai4ce/SSCBench 9e767e1 ``method/MonoScene`` (``Kitti360Dataset``);
- :mod:`occufly.datasets.compat.cgformer` -- pkqbajng/CGFormer 0331e11
  (``OccuFlyKITTI360Dataset``, mmdet registry);
- :mod:`occufly.datasets.compat.disc` -- Enyu-Liu/DISC 00ecc7f (``OccuFlyKITTI360`` + the
  Hydra callback ``Register``; DISC is built on Symphonies).

The torch-based modules need the extra ``occufly[torch]``; :mod:`.common` (geometry, 3D-2D
mapping, frustums, context-prior matrix, flips, depth consistency) is numpy only.
"""
