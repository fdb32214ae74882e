"""Developer tools: generators of the repo's derived docs."""
