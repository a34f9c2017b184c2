"""The ``adnerf`` commands, one part each (:mod:`adnerf.cli` lists them).

A part has ``register(subparsers)`` (its options; shared types and option groups in
:mod:`~adnerf.commands.options`) and ``run(args)`` (calls the room that does the work and prints
what the user needs): :mod:`~.synth`, :mod:`~.preprocess`, :mod:`~.import_adnerf`,
:mod:`~.check_preprocess`, :mod:`~.lip_signal`, :mod:`~.features`, :mod:`~.train`,
:mod:`~.render`, :mod:`~.stream`, :mod:`~.evaluate`, :mod:`~.demo`; the benchmarks' parts are in
:mod:`adnerf.bench.command`. Where a command writes is checked by :mod:`adnerf.formats.outputs`.

Beside them, what the commands do beyond parsing:

- :mod:`~adnerf.commands.render_video`: render a run driven by audio, poses and a blink track to
  frames and an mp4 (``adnerf render``); :mod:`~adnerf.commands.paste_back` puts the squares
  back into the source's frames, :mod:`~adnerf.commands.pose_edits` reads the pose edits.
- :mod:`~adnerf.commands.stream_video`: ``adnerf stream``'s loop.
- :mod:`~adnerf.commands.demo`: the end-to-end demo on the synthetic scene (``adnerf demo``).
"""
