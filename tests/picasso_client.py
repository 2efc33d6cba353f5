"""Run Picasso on a movie with a camera exported by ``emccdcal export --to picasso``.

Run as a separate process (``python picasso_client.py MOVIE GRADIENT CAMERA [CAMERA ...]``)
with ``HOME`` pointing at a directory whose ``.picasso/config.yaml`` holds the exported
cameras, so that Picasso's own configuration loader (``picasso.CONFIG``) parses it. Each
camera entry's ``Baseline``, ``Sensitivity`` and ``DefaultGain`` become ``camera_info`` as
Picasso's Localize window makes them when the camera is chosen. Prints, per camera, one
line of JSON with the localizations (frame, x, y, photons); one process for all of them,
so that Picasso's start and its numba compilation are paid once.
"""

import json
import sys


def main(movie_path, gradient, cameras):
    import picasso
    from picasso import io, localize

    movie, info = io.load_movie(movie_path)
    for camera in cameras:
        entry = picasso.CONFIG["Cameras"][camera]
        camera_info = {
            "Baseline": entry["Baseline"],
            "Sensitivity": entry["Sensitivity"],
            "Gain": entry["DefaultGain"],
            "Qe": 1,
            "Pixelsize": entry.get("Pixelsize", 130),
        }
        locs, _ = localize.localize(
            movie,
            camera_info=camera_info,
            identification_parameters={"Min. Net Gradient": gradient, "Box Size": 7},
            fitting_method="gaussmle",
            return_info=True,
        )
        print(
            json.dumps(
                {
                    "camera": camera,
                    "camera_info": camera_info,
                    "frame": locs["frame"].tolist(),
                    "x": locs["x"].tolist(),
                    "y": locs["y"].tolist(),
                    "photons": locs["photons"].tolist(),
                }
            )
        )


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3:])
