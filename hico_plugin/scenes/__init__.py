"""Built-in scenes with exact geometry, rendered by an independent analytic ray caster."""
