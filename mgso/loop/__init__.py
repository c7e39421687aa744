"""Loop closure (docs/loop.md): place recognition on keyframes (:mod:`mgso.loop.place`), Sim(3) verification
(:mod:`mgso.loop.verify`), a Sim(3) pose graph over all keyframes (:mod:`mgso.loop.graph`, GTSAM), and the loop
closer that joins them and tells the mapper how its keyframes moved (:mod:`mgso.loop.closer`)."""
