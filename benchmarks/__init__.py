"""Speed and quality measurements of kforge, side by side with Jax2D and Kinetix; each runs as
`python -m benchmarks.NAME` from the top of a checkout and imports kforge like any user, through its packages'
public surfaces. Importing this package imports nothing: the Kinetix baselines run under Kinetix's own interpreter.
"""
