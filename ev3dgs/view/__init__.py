"""`ev3dgs view`: a scene's cameras, exposure trajectories, frames and events, or a run's trained Gaussians, in
the browser (viser, optional extra ``ev3dgs[view]``) or as a static figure (``--out FILE.png``, matplotlib).

data.py prepares everything as plain numpy (no viser import; tested in the fast suite), figure.py draws the
static figure, server.py puts the same content into a viser server, live.py hooks it into `ev3dgs train --view`.
"""
