"""The evaluators, and which official evaluator each follows (its statement of conformance).

* :class:`ablate.metrics.kitti.KittiAP` (DGFN's 2D detection AP): the KITTI object devkit's
  ``cpp/evaluate_object.cpp`` of 2017, bug for bug in 2D, by default (``devkit="2017"``, evaluator
  ``kitti_object_devkit_2017``); ``devkit="2d_2012"`` keeps the older 2D-only devkit's ground-truth height rule.
  Tested on boxes on the height thresholds by hand and on random frames against a transliteration of the devkit.
* :class:`ablate.metrics.road.RoadMaxF` and :func:`ablate.metrics.road.bev_lookup` (BiFNet's MaxF, AP, PRE, REC in
  BEV): the KITTI road devkit (2013) bug for bug by default, evaluator ``kitti_road_devkit``: the measures of
  ``python/helper.py`` (``evalExp``, ``pxEval_maximizeFMeasure``) and the perspective -> BEV warp of
  ``python/transform2BEV.py`` (``BirdsEyeView.computeBEVLookUpTable``, ``transformImage2BEV``).
  ``lookup="nearest"`` keeps the nearest-pixel warp, a deviation. Tested against a loop-based reference of the
  measures, on a calibration projected by hand, and on the real road frame um_000000.
* :class:`ablate.metrics.coco.MaskAP` (SMoE's mask AP, AP50, AP75): pycocotools' ``COCOeval`` itself (pycocotools
  >= 2.0.7; COCO's 10 IoU thresholds, 101-point curve, 100 detections), with one rule of its own on top, as SMoE
  states it: a GT shorter than 25 px at 375 px (KITTI moderate) is made a crowd region (``iscrowd=1``), so it is
  neither a miss nor a reason for a FP; one exactly 25 px tall counts (>=). Tested against direct COCOeval calls
  on hand-made masks.
* ChiNet's semantic metrics (:mod:`ablate.tasks.semantic`): no official evaluator; ChiNet does not define "Det.
  Rate", read as the micro-averaged recall over the free-space and road-object pixels (torchmetrics
  ``MulticlassRecall``, background ignored), and per-class IoU (``MulticlassJaccardIndex``), the standard
  definitions. Tested by hand in tests/tasks/test_semantic.py.

Each job records the evaluator its test metrics follow as the run's ``evaluator`` tag
(:attr:`ablate.tasks.base.FusionTask.evaluator`). :data:`EVALUATORS` names today's default of each metric module
whose rule has changed since runs were made; the report (:func:`ablate.tables.provenance.provenance`) says so under a table
whose runs import such a module but did not record that evaluator. docs/metrics.md lists the same per table.
"""

#: Today's evaluator, by metric module: the ``evaluator`` tag a run of a task that builds the module's metric with
#: its defaults records. A run whose code imports the module (``ablate.tables.provenance.dependencies``) and whose tag
#: differs, or that has none (made before the tag), was scored by another rule.
EVALUATORS = {"ablate.metrics.kitti": "kitti_object_devkit_2017", "ablate.metrics.road": "kitti_road_devkit"}
