"""Measuring a talking head: held-out renders against the true frames.

- :mod:`~adnerf.evaluation.evaluate`: PSNR / SSIM on the frame, head and mouth, the landmark and
  lip-sync measures, LPIPS and SyncNet where weights are given (``adnerf evaluate``).
- :mod:`~adnerf.evaluation.landmark_metrics`: LMD and the inner-lip opening's correlation and
  offset; :mod:`~adnerf.evaluation.lpips` and :mod:`~adnerf.evaluation.syncnet`: the networks
  behind LPIPS and LSE-D / LSE-C, loaded from the user's files.
- :mod:`~adnerf.evaluation.readers`: the synthetic scene's jaw and eyes read back off renders.
"""
