"""Training helpers: seeding and RNG state, thread policy, atomic checkpoints, logging and progress."""
