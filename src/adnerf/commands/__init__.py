"""What the ``adnerf`` commands do beyond parsing (:mod:`adnerf.cli` parses and dispatches;
:mod:`adnerf.outputs` checks where every command writes).

- :mod:`~adnerf.commands.render_video`: render a run driven by audio, poses and a blink track to
  frames and an mp4 (``adnerf render``).
- :mod:`~adnerf.commands.demo`: the end-to-end demo on the synthetic scene (``adnerf demo``).
"""
