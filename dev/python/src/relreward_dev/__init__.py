"""relreward_dev: what the repository's Python scripts, tests and benchmarks share.

Not the client (that is ``relreward``, client/python): a development package, installed into
.venv by ``make setup`` (non-editable: after editing it, ``make setup`` reinstalls it), so that
scripts in different folders import one copy instead of reaching into each other's folders.

Module map:

- ``launcher``: ``Binaries`` (the checkout's relreward-server and relreward, or
  $RELREWARD_SERVER_BIN / $RELREWARD_CLI_BIN) and ``Server``, relreward-server as a child
  process on a loopback port, its address read from its first stdout line.
- ``safetensors``: the safetensors format read and written by hand (torch and numpy only).
- ``schedule``: every DDPM schedule table in float64 from the formulas.
- ``nets``: the native denoisers (Diffuser's TemporalUnet without attention, the MLP) in plain
  torch.nn, state-dict names as relreward's; ``item_shape`` of a manifest's space.
- ``reward_nets``: the relative reward networks (windowed MLP, Diffuser's ValueFunction, the
  2D conv encoder, the flat MLP).
- ``served``: a downloaded reward model as relreward serves it (network, normalizer, step
  tables), for the reference server and the in-process comparisons.
- ``unet2d``: diffusers' own UNet2DModel and DDPMScheduler configured as relreward's native
  Unet2d and linear schedule.
- ``rng``: the server's seeded generator, draw for draw, for replaying a run's noise.
- ``analytic``: the exact eps-model of Gaussian data, as a TorchScript-able module.
- ``digits``: scikit-learn's 8x8 digits scaled to [-1, 1] and split as the digits experiment
  splits them.

The reference modules are written from the papers and Diffuser's code, independently of the
Rust side, which the tests compare against them (tests/python/*_reference.py drive them).
"""
