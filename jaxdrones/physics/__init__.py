"""The pure-JAX physics core: rotations, drone params from URDFs, the state, the paper's explicit dynamics and
aerodynamics, the hand-written adjoint, the static config and its checks, the sim-to-real options, and the control
step (`jaxdrones.physics.step`). It imports nothing above itself (no env, backend, sensor or training code)."""
