"""The forward model's geometry: poses, the camera, mirrors of revolution, lasers and the rig."""
