"""``workbench track``: the frames of one scene in order, each next frame starting from the previous one's
particles and estimate, moved by the camera's motion.

- ``config``: ``TrackConfig``, the settings of a tracked frame and of lost tracking;
- ``motion``: the camera's motion between frames, given (``scene_camera_world.json``) or from the depth;
- ``lost``: which objects the carried scene no longer explains, and the words a frame's status is said in;
- ``sequence``: the frame loop (``Tracker``, ``track_frames``).
"""
