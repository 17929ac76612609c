"""egorelight: EgoRelight (egocentric capture, relightable avatars, HDR light recovery) as a tool."""

__version__ = "0.1.0"
