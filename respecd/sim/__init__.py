"""The simulated rover: a seeded world of scripted scenarios and renderers for every modality."""
