"""The sphere detector on rendered discs and on the simulator's frames: accuracy, rejections."""

import cv2
import numpy as np
import pytest
from scipy.special import erfc

from armcal_ros.frontend.detectors import SphereDetector

SHAPE = (480, 640)


def render_sphere(centre, radius, amp=180.0, bg=20.0, edge=0.8, shape=SHAPE, image=None):
    """
    Add a Gaussian-edged disc to a float image (or a flat background).

    I(r) = amp * 0.5 erfc((r - radius) / (sqrt(2) edge)): a uniform disc of ``radius`` blurred by
    a Gaussian of sigma ``edge``, sampled at pixel centres (integer coordinates).
    """
    img = np.full(shape, bg, float) if image is None else image
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    r = np.hypot(xs - centre[0], ys - centre[1])
    img += amp * 0.5 * erfc((r - radius) / (np.sqrt(2.0) * edge))
    return img


def quantise(img, rng=None, noise=3.0, dtype=np.uint8, scale=1.0):
    img = img * scale
    if rng is not None:
        img = img + rng.normal(0.0, noise * scale, img.shape)
    return np.clip(np.round(img), 0, np.iinfo(dtype).max).astype(dtype)


@pytest.fixture
def rng():
    return np.random.default_rng(42)


def test_sphere_centroid_accuracy_on_50_renders(rng):
    errors = []
    for _ in range(50):
        centre = rng.uniform([40, 40], [600, 440])
        radius = rng.uniform(3.0, 8.0)
        img = quantise(render_sphere(centre, radius, amp=rng.uniform(80, 230)), rng, noise=3.0)
        dets = SphereDetector().detect(img)
        assert len(dets) == 1
        assert dets[0].id == 0
        assert dets[0].radius_px == pytest.approx(radius, rel=0.35)
        errors.append(np.linalg.norm(dets[0].uv - centre))
    assert np.mean(errors) < 0.15
    assert np.max(errors) < 0.3


@pytest.mark.parametrize('dtype,value', [(np.uint8, 0), (np.uint8, 255), (np.uint16, 0),
                                         (np.uint16, 65535), (np.uint8, 128)])
def test_flat_frames_give_nothing(dtype, value):
    det = SphereDetector()
    assert det.detect(np.full(SHAPE, value, dtype)) == []
    assert det.detect(np.full(SHAPE + (3,), value, dtype)) == []


def test_noise_only_frame_gives_nothing(rng):
    assert SphereDetector().detect(quantise(np.full(SHAPE, 40.0), rng, noise=5.0)) == []


def test_hot_pixel_and_speck_are_rejected(rng):
    img = quantise(np.full(SHAPE, 20.0), rng)
    img[100, 200] = 255
    img[300:302, 400:402] = 255
    det = SphereDetector()
    assert det.detect(img) == []
    assert det.last_status in ('rejected', 'none')
    # ... and do not hide a real sphere, even though they are brighter
    img = quantise(render_sphere((320.3, 240.6), 5.0, amp=120), rng)
    img[100, 200] = 255
    img[300:302, 400:402] = 255
    dets = SphereDetector().detect(img)
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - (320.3, 240.6)) < 0.2


def _glint(img, start, end, width=2, value=230):
    cv2.line(img, start, end, value, width, cv2.LINE_AA)
    return img


def test_elongated_glint_is_rejected(rng):
    img = quantise(np.full(SHAPE, 20.0), rng)
    assert SphereDetector().detect(_glint(img, (100, 100), (160, 130))) == []
    img = quantise(render_sphere((420.7, 300.2), 6.0), rng)
    dets = SphereDetector().detect(_glint(img, (100, 100), (160, 130)))
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - (420.7, 300.2)) < 0.2


def test_second_smaller_dimmer_blob_is_ignored(rng):
    img = render_sphere((200.4, 150.8), 6.0, amp=200)
    img = quantise(render_sphere((450.0, 350.0), 3.0, amp=90, bg=0.0, image=img), rng)
    dets = SphereDetector().detect(img)
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - (200.4, 150.8)) < 0.2
    assert 0.5 < dets[0].quality <= 1.0


def test_two_equal_spheres_are_ambiguous_unless_tracked(rng):
    both = render_sphere((150.0, 150.0), 6.0)
    both = quantise(render_sphere((500.0, 350.0), 6.0, bg=0.0, image=both), rng)
    det = SphereDetector()
    assert det.detect(both) == []
    assert det.last_status == 'ambiguous'
    # Tracking: having seen the ball alone at (500, 350), the highlight elsewhere is ignored.
    alone = quantise(render_sphere((500.0, 350.0), 6.0), rng)
    assert len(det.detect(alone)) == 1
    dets = det.detect(both)
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - (500.0, 350.0)) < 0.2
    assert det.last_status == 'tracked'
    # A comparable highlight inside the search window: the blob at the previous position is
    # kept, flagged by a low quality; without a previous position the frame is ambiguous.
    near = render_sphere((500.0, 350.0), 6.0)
    near = quantise(render_sphere((525.0, 340.0), 6.0, amp=200, bg=0.0, image=near), rng)
    dets = det.detect(near)
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - (500.0, 350.0)) < 0.2
    assert det.last_status == 'tracked_ambiguous' and dets[0].quality < 0.2
    assert SphereDetector().detect(near) == []


def test_tracking_falls_back_to_the_whole_image(rng):
    det = SphereDetector(search_window_px=30)
    det.detect(quantise(render_sphere((100.0, 100.0), 5.0), rng))
    dets = det.detect(quantise(render_sphere((540.3, 400.1), 5.0), rng))
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - (540.3, 400.1)) < 0.2
    assert det.last_status == 'ok'
    det.reset()
    assert det.last_uv is None


def test_half_occluded_and_border_spheres_are_rejected(rng):
    img = render_sphere((300.0, 200.0), 8.0)
    img[:, 300:] = 20.0                       # right half hidden
    assert SphereDetector().detect(quantise(img, rng)) == []
    img = quantise(render_sphere((1.5, 200.0), 6.0), rng)
    assert SphereDetector().detect(img) == []


def test_sixteen_bit_and_twelve_bit_in_sixteen(rng):
    centre = (222.2, 333.3)
    base = render_sphere(centre, 5.0)
    for scale in (257.0, 16.0):              # full 16-bit range, then 12-bit data
        img = quantise(base, rng, dtype=np.uint16, scale=scale)
        dets = SphereDetector().detect(img)
        assert len(dets) == 1 and np.linalg.norm(dets[0].uv - centre) < 0.15


def test_colour_led_on_bgr_image(rng):
    centre = (123.4, 234.5)
    red = quantise(render_sphere(centre, 4.0, amp=220), rng)
    bgr = np.dstack([quantise(np.full(SHAPE, 20.0), rng),
                     quantise(np.full(SHAPE, 25.0), rng), red])
    dets = SphereDetector().detect(bgr)
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - centre) < 0.15


def test_vignetted_background(rng):
    ys, xs = np.mgrid[0:SHAPE[0], 0:SHAPE[1]]
    vignette = 60.0 * (1 - ((xs - 320) ** 2 + (ys - 240) ** 2) / (400.0 ** 2))
    centre = (580.6, 60.3)
    img = quantise(render_sphere(centre, 5.0, amp=150, bg=0.0, image=vignette.copy()), rng)
    dets = SphereDetector().detect(img)
    assert len(dets) == 1 and np.linalg.norm(dets[0].uv - centre) < 0.15


def test_size_limits(rng):
    img = quantise(render_sphere((320.0, 240.0), 20.0), rng)
    assert SphereDetector(max_radius_px=10).detect(img) == []
    assert len(SphereDetector(max_radius_px=30).detect(img)) == 1


def test_sphere_on_the_simulators_frames():
    """Frames rendered by the simulator (sensor noise, blur, vignetting, glints, occlusion)."""
    from armcal_ros.sim.cell import simulate_cell
    res = simulate_cell('geometric', seed=3, duration=6.0)
    f = res.frames
    detectors = {}
    errors, wrong, visible = [], 0, 0
    for i in range(min(len(f), 120)):
        det = detectors.setdefault(int(f.camera[i]), SphereDetector())
        dets = det.detect(res.render(i))
        if not f.visible[i]:
            continue
        visible += 1
        if dets:
            e = np.linalg.norm(dets[0].uv - f.uv[i])
            wrong += e > 1.0
            errors.append(e)
    assert visible > 50
    assert len(errors) >= 0.95 * visible
    assert wrong == 0
    assert np.median(errors) < 0.05


def _cluttered_scene(rng):
    """Return a static scene: boxes plus three marker look-alikes brighter than the marker."""
    scene = np.full(SHAPE, 50.0)
    for _ in range(30):
        x, y = rng.integers(0, 600), rng.integers(0, 440)
        scene[y:y + rng.integers(10, 80), x:x + rng.integers(10, 80)] = rng.uniform(0, 110)
    for c in ((120.0, 90.0), (400.0, 380.0), (560.0, 200.0)):
        scene = render_sphere(c, 6.0, amp=230, bg=0.0, image=scene)
    return scene


def _dwells(rng, n_dwells, frames_per_dwell):
    """Return marker positions, one per dwell, spread over the image, and frames per dwell."""
    return [rng.uniform([60, 60], [580, 420]) for _ in range(n_dwells)], frames_per_dwell


def test_static_look_alikes_and_clutter_are_ignored_once_the_scene_is_known(rng):
    scene = _cluttered_scene(rng)
    spots, per = _dwells(rng, 12, 10)
    on, off = SphereDetector(), SphereDetector(static_scene=False)
    hits = {'on': [], 'off': []}
    for k, centre in enumerate(spots):
        view = np.maximum(scene, render_sphere(centre, 5.0, amp=160, bg=0.0))  # it occludes
        for _ in range(per):
            img = quantise(view, rng, noise=2.0)
            for name, det in (('on', on), ('off', off)):
                d = det.detect(img)
                ok = len(d) == 1 and np.linalg.norm(d[0].uv - centre) < 0.5
                wrong = len(d) == 1 and not ok
                if k >= 4:          # the scene is known after 33 images
                    hits[name].append((ok, wrong))
    ok_on = np.mean([h[0] for h in hits['on']])
    assert ok_on > 0.95 and not any(h[1] for h in hits['on'])
    # the same images without the scene: a look-alike outshines the marker
    assert np.mean([h[0] for h in hits['off']]) < 0.5


def test_a_dwelling_marker_stays_out_of_the_scene(rng):
    # Dwells of 100 images (longer than the keep interval): the marker must not become
    # scenery, and subtracting a black scene must not move the centroid.
    # The scene is a median of five noisy images: subtracting it adds its noise (~0.5 of the
    # image's) to the centroid weights, ~0.005 px here; a marker in the median left a crescent
    # whose centroid was off by tenths of a pixel.
    spots, per = _dwells(rng, 3, 100)
    on, off = SphereDetector(), SphereDetector(static_scene=False)
    for centre in spots:
        clean = render_sphere(centre, 4.0, amp=150, bg=3.0)
        for _ in range(per):
            img = quantise(clean, rng, noise=1.0)
            a, b = on.detect(img), off.detect(img)
            assert len(a) == 1 and len(b) == 1
            assert np.linalg.norm(a[0].uv - b[0].uv) < 0.02
    assert on._scene is not None


def test_a_parked_marker_becomes_scenery_and_is_missed_not_mistaken(rng):
    centre = (300.0, 200.0)
    det = SphereDetector()
    statuses = []
    clean = render_sphere(centre, 4.0, amp=150, bg=3.0)
    for _ in range(2 * SphereDetector.SCENE_FORCE * SphereDetector.SCENE_EVERY):
        d = det.detect(quantise(clean, rng, noise=1.0))
        assert not d or np.linalg.norm(d[0].uv - centre) < 0.2
        statuses.append(bool(d))
    assert statuses[0] and not statuses[-1]
    # once it moves it is found again
    d = det.detect(quantise(render_sphere((420.0, 300.0), 4.0, amp=150, bg=3.0), rng, noise=1.0))
    assert len(d) == 1 and np.linalg.norm(d[0].uv - (420.0, 300.0)) < 0.2


def render_lit_ball(centre, radius, peak=160.0, ambient=0.25, light=(0.0, -0.8, 0.6),
                    shape=SHAPE, super_sampling=4):
    """
    Return (image, coverage) of a matte ball lit by one distant lamp, ``ambient`` on its far side.

    Brightness peak (ambient + (1 - ambient) max(0, n . l)) at the surface normal n = (x, y, -z)
    (image axes, z towards the camera), sampled ``super_sampling``^2 times per pixel, then
    blurred by a Gaussian of 0.8 px; ``coverage`` is the blurred disc (what the ball hides).
    """
    s = super_sampling
    light = np.asarray(light, float) / np.linalg.norm(light)
    ys, xs = np.mgrid[0:shape[0] * s, 0:shape[1] * s]
    x = ((xs + 0.5) / s - 0.5 - centre[0]) / radius
    y = ((ys + 0.5) / s - 0.5 - centre[1]) / radius
    inside = x * x + y * y < 1.0
    z = np.sqrt(np.clip(1.0 - x * x - y * y, 0.0, None))
    lit = np.clip(x * light[0] + y * light[1] - z * light[2], 0.0, None)
    ball = inside * peak * (ambient + (1.0 - ambient) * lit)
    pool = (lambda a: cv2.GaussianBlur(a.reshape(shape[0], s, shape[1], s).mean(axis=(1, 3)),
                                       (0, 0), 0.8))
    return pool(ball), pool(inside.astype(float))


@pytest.mark.parametrize('centre,radius', [('shaded', 4.0), ('centroid', 4.0), ('shaded', 2.3)])
def test_a_lamp_lit_ball_darker_than_the_scene_on_its_far_side_is_found(rng, centre, radius):
    """
    Over clutter brighter than its unlit side, the ball stands out of the scene only where lit.

    Measured on that crescent alone (the frame minus the scene, clipped at zero) it failed the
    roundness test: here 41 of 100 frames found, half the places being in front of a bright
    box (47 with the centroid).  Weighed again on where the frame differs from the scene
    either way it is the whole disc: 94 found (100 with the centroid, pulled towards the lamp
    by 1.8 px).  The crescent under-states the ball's size too, and a fit started there can
    take a smaller ball towards the lamp; started no smaller than the camera's recent fits,
    100 found, median 0.05 px off, and of a 2.3 px ball 99, median 0.09 px, within 0.4 px
    (79 found and up to 2.2 px off without that start).  The centre's noise grows as the
    ball's image shrinks, so the median's bound is 0.4 px / radius.
    """
    scene = _cluttered_scene(rng)
    spots, per = _dwells(rng, 14, 10)
    for c in spots[1::2]:        # every other place in front of a bright box
        u, v = int(c[0]), int(c[1])
        scene[v - 20:v + 20, u - 20:u + 20] = 100.0
    det = SphereDetector(centre=centre)
    found = wrong = seen = 0
    errors = []
    for k, c in enumerate(spots):
        ball, cover = render_lit_ball(c, radius, light=(0.3, -0.8, -0.5))
        view = ball + (1.0 - cover) * scene
        for _ in range(per):
            d = det.detect(quantise(view, rng, noise=2.0))
            if k < 4:          # the scene is known after 33 images
                continue
            seen += 1
            if d:
                # Within the ball's image it is the ball (the centroid of a crescent is off
                # towards the lamp); beyond, something else was taken for it.
                e = np.linalg.norm(d[0].uv - c)
                found += e < radius
                wrong += e >= radius
                errors.append(e)
    assert found > 0.9 * seen and wrong == 0, (found, wrong, seen)
    if centre == 'shaded':
        assert np.median(errors) < 0.4 / radius and max(errors) < 0.5, errors
    else:
        assert np.median(errors) > 0.3, errors        # the centroid's light bias


def test_a_smaller_ball_after_a_bigger_one_is_found_again(rng):
    """
    The camera's recent fit radii start a cold fit, but never bound it.

    A fit started from a radius far above the ball's fails; if only such starts were tried, no
    fit of the new ball would ever enter the recent radii and the camera stayed blind for good
    (a knocked camera of the lamp-lit cluttered cell, whose old scene left large blobs that
    filled them; here a tool changed to a smaller ball).  From the blob's own size it is found
    again at once.
    """
    scene = _cluttered_scene(rng)
    det = SphereDetector(centre='shaded')
    spots, per = _dwells(rng, 16, 10)
    found = []
    for k, c in enumerate(spots):
        radius = 10.0 if k < 8 else 3.0
        ball, cover = render_lit_ball(c, radius, light=(0.3, -0.8, -0.5))
        view = ball + (1.0 - cover) * scene
        for _ in range(per):
            d = det.detect(quantise(view, rng, noise=2.0))
            if k >= 8:
                found.append(bool(d) and np.linalg.norm(d[0].uv - c) < 0.5)
    assert np.mean(found) > 0.9, np.mean(found)


def test_recent_large_fits_do_not_size_the_fits_of_a_small_ball(rng, monkeypatch):
    """
    The recent radii start a cold fit no larger than 3 x the blob's own size.

    Fits taken on something large (a bright patch of a textured scene before the scene is
    known: 29-63 px where the ball has 2.7, on the simulator's lamp-lit textured PUMA cell)
    sized every later patch from their median, and each fit could double it: a frame cost 6 s
    and `armcal calibrate` of a 90 s recording did not finish in 34 min.  Here 8 places of a
    30 px ball, then a 2.5 px one: found at once, from patches sized by its own blob.
    """
    from armcal_ros.frontend.detectors import sphere
    scene = _cluttered_scene(rng)
    det = SphereDetector(centre='shaded')
    spots, per = _dwells(rng, 14, 8)
    real = sphere.fit_shaded_sphere
    sides = []

    def spy(patch, *a, **k):
        sides.append(max(patch.shape))
        return real(patch, *a, **k)
    monkeypatch.setattr(sphere, 'fit_shaded_sphere', spy)
    found, small = [], []
    big = None
    for k, c in enumerate(spots):
        radius = 30.0 if k < 8 else 2.5
        if k == 8:
            big = np.median(det._radii)
        ball, cover = render_lit_ball(c, radius, light=(0.3, -0.8, -0.5))
        view = ball + (1.0 - cover) * scene
        for _ in range(per):
            del sides[:]
            d = det.detect(quantise(view, rng, noise=2.0))
            if k >= 8:
                found.append(bool(d) and np.linalg.norm(d[0].uv - c) < 0.5)
                small.extend(sides)
    assert big > 25, big                        # the recent fits are the large ball's
    # Without the bound: 0.75 found, from patches and starts sized by the large ball.
    assert np.mean(found) > 0.9, np.mean(found)
    # 2 (3 x the blob's moments radius, ~2.7 px, + 3) + 1 = 23, against 67 from the recent
    # 30 px.
    assert small and max(small) <= 25, sorted(set(small))


def test_a_difference_without_a_size_does_not_end_the_search(rng, monkeypatch):
    """
    Where |frame - scene| stands out in a pixel only, the fit starts from the blob's size.

    Its moments then have no size (0), and a start radius of 0 raised out of the detector and
    ended a whole `armcal calibrate` run on a lamp-lit recording with a textured scene.
    """
    from armcal_ros.frontend.detectors import sphere
    scene = _cluttered_scene(rng)
    det = SphereDetector(centre='shaded')
    spots, per = _dwells(rng, 10, 10)
    real = sphere._moments
    sizeless = []

    def moments(patch, u0, v0):
        got = real(patch, u0, v0)
        if got is None or len(sizeless) % 2:
            return got
        sizeless.append(1)
        return got[0], 0.0
    monkeypatch.setattr(sphere, '_moments', moments)
    found = []
    for k, c in enumerate(spots):
        ball, cover = render_lit_ball(c, 6.0, light=(0.3, -0.8, -0.5))
        view = ball + (1.0 - cover) * scene
        for _ in range(per):
            d = det.detect(quantise(view, rng, noise=2.0))
            if k >= 4:
                found.append(bool(d) and np.linalg.norm(d[0].uv - c) < 0.5)
    assert sizeless and np.mean(found) > 0.9, (len(sizeless), np.mean(found))


def _shifted(image, shift):
    """Return ``image`` with its content moved by ``shift`` (px; sub-pixel, edges repeated)."""
    M = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    return cv2.warpAffine(np.float32(image), M, (image.shape[1], image.shape[0]),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _run_knock(rng, det, scene, shift, n_before=12, n_after=12, per=10, gain=1.0):
    """Dwells over ``scene``, then over it shifted by ``shift``: each frame's error after (px)."""
    after = []
    spots, _ = _dwells(rng, n_before + n_after, per)
    for k, centre in enumerate(spots):
        knocked = k >= n_before
        view = _shifted(scene, shift) if knocked else scene
        view = np.maximum(view, render_sphere(centre, 5.0, amp=160, bg=0.0)) * (
            gain if knocked else 1.0)
        for _ in range(per):
            d = det.detect(quantise(view, rng, noise=2.0))
            if knocked:
                after.append(np.linalg.norm(d[0].uv - centre) if d else np.nan)
    return np.array(after)


def test_the_static_scene_follows_a_knocked_camera(rng):
    """
    The clutter behind a knocked camera moves by pixels: the scene must move with it.

    Without that the old scene's subtraction leaves every edge of the clutter as a blob for
    as long as the scene takes to be learnt again.  With it the scene is shifted within two
    checks (16 images): from then on the marker is found as before, within 1 px at once (the
    shifted scene's edges are the old ones interpolated) and within 0.5 px once the scene is
    learnt again from new images (five, kept every eighth image).
    """
    scene = _cluttered_scene(rng)
    shift = (3.4, -2.2)             # 0.25 deg at f = 800 px is 3.5 px
    follow = SphereDetector()
    after = _run_knock(np.random.default_rng(7), follow, scene, shift)
    assert follow.scene_moves == 1
    np.testing.assert_allclose(follow.last_scene_shift, shift, atol=0.1)
    moved = 2 * SphereDetector.SCENE_CHECK_EVERY
    learnt = moved + SphereDetector.SCENE_FRAMES * SphereDetector.SCENE_EVERY_FIRST
    assert np.isfinite(after[moved:]).mean() > 0.95
    assert np.nanmax(after[moved:]) < 1.0 and np.nanmax(after[learnt:]) < 0.5
    # The same images with the scene left where it was: the marker's views lost or mistaken
    # (on this scene the search locks on to an edge of the clutter hundreds of pixels away).
    stay = SphereDetector()
    stay.SCENE_CHECK_EVERY = 10 ** 9
    lost = _run_knock(np.random.default_rng(7), stay, scene, shift)[moved:]
    assert np.mean(lost < 1.0) < 0.8


def test_an_exposure_step_or_a_still_camera_does_not_move_the_scene(rng):
    """No shift, only the light 1.5 x: the scene stays put (phase correlation ignores gain)."""
    det = SphereDetector()
    after = _run_knock(rng, det, _cluttered_scene(rng), (0.0, 0.0), gain=1.5)
    assert det.scene_moves == 0
    assert not np.any(after > 0.5)


@pytest.mark.parametrize('gain', [1.5, 0.7, 2.0])
def test_an_exposure_step_over_clutter_is_followed_at_once(gain):
    """
    Auto-exposure steps the whole frame: the scene is scaled by the frame's exposure.

    Subtracted unscaled, a 1.5 x step left the bright clutter standing out of the difference
    until the scene was learnt again: of the next 200 images 30 % gave the marker within
    0.5 px and 70 % something else, a pixel or more off.  Scaled, the images after a step are
    read as those of the same scene without one (the same detections), whatever the step.
    """
    def run(g):
        rng = np.random.default_rng(3)
        det = SphereDetector()
        after = _run_knock(rng, det, _cluttered_scene(rng), (0.0, 0.0), gain=g, n_after=20)
        return det, after
    _, same = run(1.0)
    det, after = run(gain)
    assert det.exposure == pytest.approx(gain, rel=0.01)
    found = np.isfinite(after) & (after < 0.5)
    assert found.mean() >= np.mean(np.isfinite(same) & (same < 0.5)) - 0.01 > 0.8
    assert np.mean(after > 1.0) <= np.mean(same > 1.0) + 0.01
