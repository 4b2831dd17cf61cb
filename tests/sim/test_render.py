"""Camera model and ray-cast rendering: analytic depths, reference == batched, texture."""

from __future__ import annotations

import math

import pytest
import torch

from sim.camera import CameraModel, camera_pose, sample_mount_jitter
from sim.render import (
    DEPTH_REL_TOLERANCE,
    GRAY_TOLERANCE_LEVELS,
    MAX_MISMATCH_FRACTION,
    RenderOutput,
    render,
    render_reference,
    render_torch,
)
from sim.rotations import euler_from_quat, quat_from_euler, quat_from_yaw, quat_rotate
from sim.world import WorldBatch, make_worlds

CAMERA = CameraModel()
# render is the numba kernel on the CPU; render_torch (the CUDA path) is tested here on the CPU.
FAST_RENDERERS = [render, render_torch]
RENDERERS = [render_reference, *FAST_RENDERERS]


def room_world(boxes: list[tuple[tuple[float, float, float], tuple[float, float, float], float, bool]] = (),
               texture_seed: int = 0) -> WorldBatch:
    """Room 10 x 6 x 4 m with the given (center, half extents, yaw, valid) boxes."""
    n = len(boxes)
    return WorldBatch(
        room_size_m=torch.tensor([[10.0, 6.0, 4.0]]),
        box_center_m=torch.tensor([[b[0] for b in boxes]]).reshape(1, n, 3),
        box_half_extent_m=torch.tensor([[b[1] for b in boxes]]).reshape(1, n, 3),
        box_yaw_rad=torch.tensor([[b[2] for b in boxes]]).reshape(1, n),
        box_valid=torch.tensor([[b[3] for b in boxes]], dtype=torch.bool).reshape(1, n),
        start_m=torch.tensor([[1.0, 3.0, 2.0]]),
        goal_m=torch.tensor([[9.5, 3.0, 2.0]]),
        texture_seed=torch.tensor([texture_seed]),
    )


def pose(x: float, y: float, z: float, roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0):
    r, p, w = (torch.tensor([v]) for v in (roll, pitch, yaw))
    return torch.tensor([[x, y, z]]), quat_from_euler(r, p, w)


def pixel_rays_forward_unit(camera: CameraModel) -> torch.Tensor:
    """[H, W, 3] rays in frame C with forward component 1, straight from the intrinsics."""
    u = torch.arange(camera.width_px, dtype=torch.float64) + 0.5
    v = torch.arange(camera.height_px, dtype=torch.float64) + 0.5
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    right = (uu - camera.cx_px) / camera.fx_px
    down = (vv - camera.cy_px) / camera.fy_px
    return torch.stack([torch.ones_like(uu), -right, -down], -1)


def assert_match(ref: RenderOutput, fast: RenderOutput) -> None:
    assert fast.depth_m.dtype == torch.float32 and fast.gray_u8.dtype == torch.uint8
    assert fast.depth_m.shape == ref.depth_m.shape == fast.gray_u8.shape
    rel = (fast.depth_m.double() - ref.depth_m.double()).abs() / ref.depth_m.double()
    assert float((rel > DEPTH_REL_TOLERANCE).double().mean()) <= MAX_MISMATCH_FRACTION, float(rel.max())
    gray_diff = (fast.gray_u8.int() - ref.gray_u8.int()).abs()
    assert float((gray_diff > GRAY_TOLERANCE_LEVELS).double().mean()) <= MAX_MISMATCH_FRACTION


# Camera model.


def test_camera_intrinsics_and_rays() -> None:
    assert (CAMERA.width_px, CAMERA.height_px) == (212, 120)
    rays = CAMERA.ray_directions(dtype=torch.float64)
    assert rays.shape == (120, 212, 3)
    assert torch.allclose(rays.norm(dim=-1), torch.ones(120, 212, dtype=torch.float64))
    # u to the right = -y (left) in FLU, v down = -z.
    assert rays[60, 0, 1] > 0 and rays[60, -1, 1] < 0 and rays[0, 106, 2] > 0 and rays[-1, 106, 2] < 0
    # The outer pixel edges span the HFOV; the outermost pixel centres sit half a pixel inside.
    assert 2 * math.atan(CAMERA.cx_px / CAMERA.fx_px) == pytest.approx(CAMERA.hfov_rad, abs=1e-12)
    inner = math.atan((CAMERA.width_px / 2 - 0.5) / CAMERA.fx_px)
    azimuth = torch.atan2(rays[..., 1], rays[..., 0])
    assert torch.allclose(azimuth[:, 0], torch.tensor(inner, dtype=torch.float64))
    assert torch.allclose(azimuth[:, -1], torch.tensor(-inner, dtype=torch.float64))
    # z-depth factor = cosine to the optical axis; projecting a ray gives its pixel centre back.
    assert torch.allclose(CAMERA.z_factor(dtype=torch.float64), rays[..., 0])
    k = CAMERA.intrinsics()
    rdf = torch.stack([-rays[..., 1], -rays[..., 2], rays[..., 0]], -1)  # right, down, forward
    pixel = (rdf @ k.T)[..., :2] / rdf[..., 2:]
    assert torch.allclose(pixel[7, 11], torch.tensor([11.5, 7.5], dtype=torch.float64))


def test_camera_pose_mount_offset_and_jitter() -> None:
    pos, quat = pose(2.0, 3.0, 1.0, yaw=math.pi / 2)
    cam_pos, cam_quat = camera_pose(pos, quat, CAMERA)
    assert torch.allclose(cam_pos, torch.tensor([[2.0, 3.1, 1.0]]), atol=1e-6)
    assert torch.equal(cam_quat, quat)
    jitter = sample_mount_jitter(256, torch.Generator().manual_seed(0))
    again = sample_mount_jitter(256, torch.Generator().manual_seed(0))
    assert torch.equal(jitter.quat_body_cam, again.quat_body_cam)
    assert float(jitter.offset_body_flu_m.abs().max()) <= 0.05
    angles = euler_from_quat(jitter.quat_body_cam)
    assert float(angles.abs().max()) <= math.radians(3.0) + 1e-6
    assert float(angles.abs().max()) > math.radians(2.5)
    jittered_pos, jittered_quat = camera_pose(pos.expand(256, 3), quat.expand(256, 4), CAMERA, jitter)
    assert float((jittered_pos - cam_pos).norm(dim=-1).max()) <= 0.05 * math.sqrt(3) + 1e-6
    forward = quat_rotate(jittered_quat, torch.tensor([1.0, 0.0, 0.0]).expand(256, 3))
    off_axis = torch.acos((forward @ torch.tensor([0.0, 1.0, 0.0])).clamp(-1, 1))
    assert float(off_axis.max()) <= math.radians(3.0) * math.sqrt(3) + 1e-4


# Analytic scenes.


@pytest.mark.parametrize("renderer", RENDERERS)
def test_facing_a_wall_gives_constant_z_depth(renderer) -> None:
    cam_pos, quat = pose(9.0, 3.0, 2.0)  # 1 m from the wall x = 10; the image sees only that wall
    out = renderer(room_world(), cam_pos, quat, CAMERA)
    assert out.depth_m.shape == (1, 120, 212)
    assert torch.allclose(out.depth_m, torch.ones_like(out.depth_m), atol=1e-5)


@pytest.mark.parametrize("renderer", RENDERERS)
@pytest.mark.parametrize("roll, pitch, yaw", [(0.0, 0.0, 0.0), (0.2, -0.3, 0.5), (-0.4, 0.25, -2.8)])
def test_tilted_camera_sees_analytic_plane_depth(renderer, roll: float, pitch: float, yaw: float) -> None:
    """Camera in the room centre: every pixel's z-depth is the distance to whichever face its ray
    reaches first, computed plane by plane from the intrinsics."""
    cam_pos, quat = pose(5.0, 3.0, 2.0, roll, pitch, yaw)
    rays = quat_rotate(quat.double().view(1, 1, 4).expand(120, 212, 4), pixel_rays_forward_unit(CAMERA))
    room = torch.tensor([10.0, 6.0, 4.0], dtype=torch.float64)
    origin = cam_pos[0].double()
    # Forward-unit rays: the ray parameter to a plane is already the z-depth.
    to_far = (room - origin) / rays
    to_near = -origin / rays
    expected = torch.where(rays > 0, to_far, to_near).amin(dim=-1)
    out = renderer(room_world(), cam_pos, quat, CAMERA)
    assert torch.allclose(out.depth_m[0].double(), expected, rtol=1e-5)


@pytest.mark.parametrize("renderer", RENDERERS)
def test_box_in_front_shows_at_its_distance(renderer) -> None:
    panel = ((5.0, 3.0, 2.0), (0.05, 0.6, 1.5), 0.0, True)
    cam_pos, quat = pose(2.0, 3.0, 2.0)
    out = renderer(room_world([panel]), cam_pos, quat, CAMERA)
    depth = out.depth_m[0]
    assert float(depth[60, 106]) == pytest.approx(5.0 - 0.05 - 2.0, abs=1e-5)
    # The panel spans +-0.6 m laterally at 2.95 m: columns within that are on it, the rest see the far wall.
    lateral_m = (torch.arange(212) + 0.5 - CAMERA.cx_px) / CAMERA.fx_px * 2.95
    on_panel = lateral_m.abs() < 0.6 - 0.02
    off_panel = lateral_m.abs() > 0.6 + 0.02
    assert torch.allclose(depth[60, on_panel], torch.full((int(on_panel.sum()),), 2.95), atol=1e-5)
    assert torch.all(depth[60, off_panel] > 2.95 + 0.2)

    turned = ((5.0, 3.0, 2.0), (0.05, 0.6, 1.5), math.pi / 2, True)  # now 1.2 m deep along x
    out = renderer(room_world([turned]), cam_pos, quat, CAMERA)
    assert float(out.depth_m[0, 60, 106]) == pytest.approx(5.0 - 0.6 - 2.0, abs=1e-5)


@pytest.mark.parametrize("renderer", RENDERERS)
def test_padding_slots_and_boxes_around_the_camera_are_invisible(renderer) -> None:
    cam_pos, quat = pose(2.0, 3.0, 2.0)
    empty = renderer(room_world(), cam_pos, quat, CAMERA)
    padded = renderer(room_world([((4.0, 3.0, 2.0), (0.5, 0.5, 0.5), 0.0, False)]), cam_pos, quat, CAMERA)
    assert torch.equal(padded.depth_m, empty.depth_m) and torch.equal(padded.gray_u8, empty.gray_u8)
    around = renderer(room_world([((2.0, 3.0, 2.0), (0.3, 0.3, 0.3), 0.4, True)]), cam_pos, quat, CAMERA)
    assert torch.allclose(around.depth_m, empty.depth_m, rtol=1e-6)


# Reference == fast paths.


def random_scene(levels: list[int], seed: int):
    """Worlds at the given levels; cameras anywhere in the room, tilted up to 0.6 rad, any yaw."""
    world = make_worlds(levels, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    batch = world.batch_size
    pos = torch.rand(batch, 3, generator=gen) * (world.room_size_m - 0.4) + 0.2
    angles = (torch.rand(batch, 3, generator=gen) * 2 - 1) * torch.tensor([0.6, 0.6, math.pi])
    return world, pos, quat_from_euler(*angles.unbind(-1))


def close_to_box_scene(levels: list[int], seed: int):
    """Worlds at the given levels; each camera within 0.3 m of one of its env's boxes (sometimes
    inside it, or beside it with the box across the camera plane), looking roughly at its centre
    (within 0.7 rad), rolled by any angle."""
    world = make_worlds(levels, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    batch = world.batch_size
    slot = (torch.rand(batch, generator=gen) * world.obstacle_count()).long()
    rows = torch.arange(batch)
    half = world.box_half_extent_m[rows, slot]
    offset_box = (torch.rand(batch, 3, generator=gen) * 2 - 1) * (half + 0.3)
    offset_enu = quat_rotate(quat_from_yaw(world.box_yaw_rad[rows, slot]), offset_box)
    pos = (world.box_center_m[rows, slot] + offset_enu).clamp(min=torch.tensor(0.01), max=world.room_size_m - 0.01)
    to_box = -offset_enu
    yaw = torch.atan2(to_box[:, 1], to_box[:, 0])
    pitch = -torch.atan2(to_box[:, 2], to_box[:, :2].norm(dim=-1))  # positive pitch is nose down
    jitter = (torch.rand(batch, 3, generator=gen) * 2 - 1) * torch.tensor([math.pi, 0.7, 0.7])
    return world, pos, quat_from_euler(jitter[:, 0], pitch + jitter[:, 1], yaw + jitter[:, 2])


SCENES = {
    "random poses": lambda: random_scene([0, 3, 8, 14, 20, 26], seed=17),
    "close to boxes": lambda: close_to_box_scene([1, 5, 12, 26, 26, 33, 40, 8], seed=5),
}


@pytest.fixture(scope="module", params=list(SCENES))
def scene_and_reference(request):
    """(world, cam_pos_enu_m, cam_quat_enu_flu, reference render), rendered once per module."""
    world, pos, quat = SCENES[request.param]()
    return world, pos, quat, render_reference(world, pos, quat, CAMERA)


def test_close_to_box_scene_sees_boxes_up_close() -> None:
    world, pos, quat = SCENES["close to boxes"]()
    nearest_m = render(world, pos, quat, CAMERA).depth_m.amin(dim=(1, 2))
    assert int((nearest_m < 0.5).sum()) >= 6, nearest_m


@pytest.mark.parametrize("renderer", FAST_RENDERERS)
def test_fast_equals_reference_on_cpu(renderer, scene_and_reference) -> None:
    world, pos, quat, reference = scene_and_reference
    assert_match(reference, renderer(world, pos, quat, CAMERA))


@pytest.mark.parametrize("renderer", FAST_RENDERERS)
def test_fast_equals_reference_for_another_camera(renderer) -> None:
    camera = CameraModel(width_px=64, height_px=36, hfov_rad=1.2)
    for world, pos, quat in (scene() for scene in SCENES.values()):
        assert_match(render_reference(world, pos, quat, camera), renderer(world, pos, quat, camera))


def test_cpu_render_does_not_depend_on_the_thread_count() -> None:
    world, pos, quat = random_scene([26] * 4, seed=8)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = render(world, pos, quat, CAMERA)
        torch.set_num_threads(2)
        two = render(world, pos, quat, CAMERA)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one.depth_m, two.depth_m) and torch.equal(one.gray_u8, two.gray_u8)


def test_chunked_torch_render_equals_one_chunk() -> None:
    world, pos, quat = random_scene([2, 9, 5], seed=4)
    whole = render_torch(world, pos, quat, CAMERA)
    chunked = render_torch(world, pos, quat, CAMERA, max_chunk_elements=1)
    assert torch.equal(whole.depth_m, chunked.depth_m) and torch.equal(whole.gray_u8, chunked.gray_u8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fast_on_cuda_equals_reference_on_cpu(scene_and_reference) -> None:
    world, pos, quat, reference = scene_and_reference
    on_gpu = render(world.to("cuda"), pos.cuda(), quat.cuda(), CAMERA)
    assert on_gpu.depth_m.device.type == "cuda"
    assert_match(reference, RenderOutput(on_gpu.depth_m.cpu(), on_gpu.gray_u8.cpu()))


# Texture.


@pytest.mark.parametrize(
    "name, cam, boxes",
    [
        ("far wall", pose(8.5, 3.0, 2.0), []),
        ("near wall (unlit)", pose(1.5, 3.0, 2.0, yaw=math.pi), []),
        ("side wall", pose(5.0, 4.5, 2.0, yaw=math.pi / 2), []),
        ("floor", pose(5.0, 3.0, 1.5, pitch=math.pi / 2), []),
        ("ceiling", pose(5.0, 3.0, 2.5, pitch=-math.pi / 2), []),
        ("box face", pose(4.0, 3.0, 2.0), [((5.0, 3.0, 2.0), (0.5, 1.5, 1.5), 0.0, True)]),
    ],
)
def test_every_surface_is_textured(name: str, cam, boxes) -> None:
    """Each view is filled by one surface; its gray values must vary (not a flat shade)."""
    out = render(room_world(boxes, texture_seed=123), *cam, CAMERA)
    gray = out.gray_u8.float()
    assert float(out.depth_m.max()) <= 1.6, f"{name}: the view must see one surface only"
    assert float(gray.std()) > 6.0, name
    assert int(torch.unique(out.gray_u8).numel()) > 30, name


def test_texture_is_deterministic_and_differs_by_surface_and_seed() -> None:
    cam = pose(5.0, 3.0, 2.0, yaw=0.7)
    a = render(room_world(texture_seed=5), *cam, CAMERA)
    b = render(room_world(texture_seed=5), *cam, CAMERA)
    c = render(room_world(texture_seed=6), *cam, CAMERA)
    assert torch.equal(a.gray_u8, b.gray_u8)
    assert torch.equal(a.depth_m, c.depth_m) and not torch.equal(a.gray_u8, c.gray_u8)
    # Two walls at the same distance look different.
    east = render(room_world(texture_seed=5), *pose(8.5, 3.0, 2.0), CAMERA).gray_u8.float()
    north = render(room_world(texture_seed=5), *pose(5.0, 4.5, 2.0, yaw=math.pi / 2), CAMERA).gray_u8.float()
    assert float((east - north).abs().mean()) > 10.0


def test_render_follows_the_body_yaw() -> None:
    """Turning the camera by 180 degrees about z in the room centre mirrors the view's depth."""
    world = room_world()
    ahead = render(world, torch.tensor([[5.0, 3.0, 2.0]]), quat_from_yaw(torch.tensor([0.0])), CAMERA).depth_m
    behind = render(world, torch.tensor([[5.0, 3.0, 2.0]]), quat_from_yaw(torch.tensor([math.pi])), CAMERA).depth_m
    assert torch.allclose(ahead, behind, rtol=1e-5)  # the room is symmetric about its centre in x and y
