"""The talking-head model, its data, training and run folder.

- :mod:`~adnerf.model.conditions`: what a frame is conditioned on (audio code, head pose, eye
  openness), :class:`~adnerf.model.conditions.FrameCondition`.
- :mod:`~adnerf.model.layers`: a radiance layer (its space, box, samples, occupancy grid, fields
  and conditions); :mod:`~adnerf.model.talking_head`: the audio encoders and the stack of layers
  (head, torso) over a plate.
- :mod:`~adnerf.model.blinks`: eye-openness tracks (natural blinks, ``--blink`` choices).
- the dataset folder a clip is preprocessed into is :mod:`adnerf.formats.dataset`'s (re-exported
  as :mod:`adnerf.model.data`).
- :mod:`~adnerf.model.train_config`, :mod:`~adnerf.model.train`,
  :mod:`~adnerf.model.distributed`: the schedule, the training loop (one or several processes).
- :mod:`~adnerf.model.run_folder`: what a trained run is on disk and how it is loaded.
"""
