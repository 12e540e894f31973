"""Tables of successor features: sparse storage, the table network, Dyna planning on an empirical model, replay
pooled across a run's iterations. Nothing here knows SB3's algorithms: :mod:`sb3_sfgpi.sfdqn` builds on it."""
