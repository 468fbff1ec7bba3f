"""Scene sources: WOMD loaders, the procedural generator, the packed store and the sampler."""
