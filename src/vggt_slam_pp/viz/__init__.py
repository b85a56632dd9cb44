"""For people: the HTML run report (:mod:`~vggt_slam_pp.viz.report`) and the 3-D web viewer
(:mod:`~vggt_slam_pp.viz.viewer`, needs the ``viz`` extra), both reading a run's folder
(:mod:`~vggt_slam_pp.viz.run_folder`)."""
