"""Run Picasso on a movie with a camera exported by ``emccdcal export --to picasso``.

Run as a separate process (``python picasso_client.py CONFIG_HOME MOVIE CAMERA GRADIENT``)
with ``HOME`` pointing at a directory whose ``.picasso/config.yaml`` is the exported file,
so that Picasso's own configuration loader (``picasso.CONFIG``) parses it. The camera
entry's ``Baseline``, ``Sensitivity`` and ``DefaultGain`` become ``camera_info`` as
Picasso's Localize window makes them when the camera is chosen. Prints the localizations
(frame, x, y, photons) as JSON on stdout.
"""

import json
import sys


def main(movie_path, camera, gradient):
    import picasso
    from picasso import io, localize

    entry = picasso.CONFIG["Cameras"][camera]
    camera_info = {"Baseline": entry["Baseline"], "Sensitivity": entry["Sensitivity"],
                   "Gain": entry["DefaultGain"], "Qe": 1,
                   "Pixelsize": entry.get("Pixelsize", 130)}
    movie, info = io.load_movie(movie_path)
    locs, _ = localize.localize(
        movie, camera_info=camera_info,
        identification_parameters={"Min. Net Gradient": gradient, "Box Size": 7},
        fitting_method="gaussmle", return_info=True)
    print(json.dumps({"camera_info": camera_info,
                      "frame": locs["frame"].tolist(), "x": locs["x"].tolist(),
                      "y": locs["y"].tolist(), "photons": locs["photons"].tolist()}))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]))
