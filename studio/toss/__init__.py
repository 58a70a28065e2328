"""The ball toss: toss primitives, lift detection, recordings and the toss model used by evaluation.

One concept per module:

- :mod:`~studio.toss.release`: when the ball leaves the cup (:func:`~studio.toss.release.find_release`);
- :mod:`~studio.toss.lift_profile`: the cup's vertical motion (:class:`~studio.toss.lift_profile.LiftProfile`);
- :mod:`~studio.toss.primitive`: the toss primitive (:class:`~studio.toss.primitive.TossPrimitive`);
- :mod:`~studio.toss.design`: what a toss should do (:class:`~studio.toss.design.TossDesign`);
- :mod:`~studio.toss.synthesis`: :func:`~studio.toss.synthesis.make_toss`, with the arm
  kinematics of :mod:`~studio.toss.arm`, the lift line of :mod:`~studio.toss.lift_path`
  and the checks of :mod:`~studio.toss.checks`;
- :mod:`~studio.toss.flight`: spinless flights of the tossed ball;
- :mod:`~studio.toss.recordings`: recordings and their CSV format;
- :mod:`~studio.toss.noise`, :mod:`~studio.toss.synthetic`: synthetic recordings;
- :mod:`~studio.toss.alignment`, :mod:`~studio.toss.smoothing`, :mod:`~studio.toss.lift_time`,
  :mod:`~studio.toss.local_fit`: the steps of the toss model;
- :mod:`~studio.toss.model`: the toss model (:class:`~studio.toss.model.TossModel`);
- :mod:`~studio.toss.defaults`: the shipped tosses (:func:`~studio.toss.defaults.load_default_toss_model`,
  ``serve-studio toss --generate``); :mod:`~studio.toss.report`: their summary.
"""
