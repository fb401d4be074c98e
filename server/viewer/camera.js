// The viewer's camera: an orbit about a target point, with pan and zoom, in the scene frame of
// docs/api.md (the first context camera's, OpenCV axes: x right, y down, z forward). At rest it
// is that camera itself (identity world-to-camera) looking at a target straight ahead, so the
// first view is what the server renders by default. Intrinsics are C4G's, as fractions of the
// image size (the render request's form).

/** fx = fy = 0.8767 of the image size, principal point centred (NormalizedIntrinsics::C4G_DEFAULT). */
export const C4G_INTRINSICS = Object.freeze({ fx: 0.8767, fy: 0.8767, cx: 0.5, cy: 0.5 });

const ORBIT_RADIANS_PER_PIXEL = 0.005;
const PITCH_LIMIT = 1.5;

export class OrbitCamera {
  constructor() {
    this.home(2);
    this.onchange = null;
  }

  /** The first context camera, orbiting about the point `depth` straight ahead. */
  home(depth) {
    this.homeDepth = depth;
    this.target = [0, 0, depth];
    this.distance = depth;
    this.yaw = 0;
    this.pitch = 0;
    this.changed();
  }

  changed() {
    this.onchange?.();
  }

  /** World-to-camera rotation, row-major 3×3: Rx(pitch) · Ry(yaw). */
  rotation() {
    const [cy, sy] = [Math.cos(this.yaw), Math.sin(this.yaw)];
    const [cp, sp] = [Math.cos(this.pitch), Math.sin(this.pitch)];
    // Rx = [[1,0,0],[0,cp,-sp],[0,sp,cp]], Ry = [[cy,0,sy],[0,1,0],[-sy,0,cy]].
    return [cy, 0, sy, sp * sy, cp, -sp * cy, -cp * sy, sp, cp * cy];
  }

  /** The camera centre in the world: the target, `distance` behind along the view axis. */
  centre() {
    const r = this.rotation();
    // Camera-to-world rotation is Rᵀ; the view axis (0, 0, 1) in the world is R's third row.
    return [0, 1, 2].map((k) => this.target[k] - this.distance * r[6 + k]);
  }

  /** World-to-camera, row-major 4×4 (the render request's `world_to_camera`). */
  worldToCamera() {
    const r = this.rotation();
    const c = this.centre();
    const t = [0, 1, 2].map((row) => -(r[3 * row] * c[0] + r[3 * row + 1] * c[1] + r[3 * row + 2] * c[2]));
    return [r[0], r[1], r[2], t[0], r[3], r[4], r[5], t[1], r[6], r[7], r[8], t[2], 0, 0, 0, 1];
  }

  /** The view for the rasterizer at `width` × `height`: rotation, translation, pixel intrinsics. */
  view(width, height) {
    const m = this.worldToCamera();
    return {
      rotation: [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]],
      translation: [m[3], m[7], m[11]],
      fx: C4G_INTRINSICS.fx * width,
      fy: C4G_INTRINSICS.fy * height,
      cx: C4G_INTRINSICS.cx * width,
      cy: C4G_INTRINSICS.cy * height,
      width,
      height,
    };
  }

  /** Turns about the target: dragging right turns the scene right, down tips it down. */
  orbit(dxPixels, dyPixels) {
    this.yaw -= dxPixels * ORBIT_RADIANS_PER_PIXEL;
    this.pitch = Math.max(-PITCH_LIMIT, Math.min(PITCH_LIMIT, this.pitch + dyPixels * ORBIT_RADIANS_PER_PIXEL));
    this.changed();
  }

  /** Slides the target across the view so the scene follows the pointer (`focalPixels`: fx). */
  pan(dxPixels, dyPixels, focalPixels) {
    const r = this.rotation();
    const scale = this.distance / focalPixels;
    for (let k = 0; k < 3; k++) this.target[k] -= scale * (dxPixels * r[k] + dyPixels * r[3 + k]);
    this.changed();
  }

  /** Moves towards the target (factor < 1) or away from it. */
  zoom(factor) {
    this.distance = Math.max(0.02 * this.homeDepth, Math.min(50 * this.homeDepth, this.distance * factor));
    this.changed();
  }

  /** Mouse and wheel on `element`: left drag orbits, right or shift drag pans, the wheel zooms. */
  attach(element, focalPixels) {
    let last = null;
    element.addEventListener('contextmenu', (e) => e.preventDefault());
    element.addEventListener('pointerdown', (e) => {
      last = { x: e.clientX, y: e.clientY, pan: e.button === 2 || e.shiftKey };
      element.setPointerCapture(e.pointerId);
    });
    element.addEventListener('pointermove', (e) => {
      if (!last) return;
      const [dx, dy] = [e.clientX - last.x, e.clientY - last.y];
      last.x = e.clientX;
      last.y = e.clientY;
      if (last.pan) this.pan(dx, dy, focalPixels());
      else this.orbit(dx, dy);
    });
    const end = () => {
      last = null;
    };
    element.addEventListener('pointerup', end);
    element.addEventListener('pointercancel', end);
    element.addEventListener(
      'wheel',
      (e) => {
        e.preventDefault();
        this.zoom(Math.exp(e.deltaY * 0.001));
      },
      { passive: false },
    );
  }
}
