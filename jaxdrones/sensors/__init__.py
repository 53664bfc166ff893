"""What the drones sense, in pure JAX: per-drone cameras (`camera`: RGB, depth and segmentation) and their ray caster
(`raycast`)."""
