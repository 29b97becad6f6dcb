"""The pipeline under the sessions: the GPU queue that owns the render device, image and video
encoders, and batch jobs that render whole trajectories."""
