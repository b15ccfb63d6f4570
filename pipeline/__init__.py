"""skyroute.pipeline: scenario settings, the content-addressed zarr cache, the stage graph and the CLI."""
