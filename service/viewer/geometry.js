// Poses and cameras, in the project's conventions (docs/design.md §2): metres and radians; OpenCV camera
// frame (x right, y down, z forward); T_cam_obj maps object-frame points into the camera frame.
// Matrices are row-major arrays of rows ([[r00, r01, r02, t0], ...]), as on the wire.

const DEG = Math.PI / 180;

export function degrees(radians) { return radians / DEG; }
export function radians(degrees) { return degrees * DEG; }

function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
function scale(a, s) { return [a[0] * s, a[1] * s, a[2] * s]; }
function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
function normalize(a) { const n = Math.hypot(a[0], a[1], a[2]) || 1; return scale(a, 1 / n); }

/** R [3x3] times v [3]. */
export function apply(R, v) {
  return [0, 1, 2].map((i) => R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2]);
}

/** A [3x3] times B [3x3]. */
export function matmul3(A, B) {
  return [0, 1, 2].map((i) => [0, 1, 2].map((j) => A[i][0] * B[0][j] + A[i][1] * B[1][j] + A[i][2] * B[2][j]));
}

/** The rotation [3x3] and translation [3] of a 4x4 pose. */
export function split(T) {
  return { R: T.slice(0, 3).map((row) => row.slice(0, 3)), t: T.slice(0, 3).map((row) => row[3]) };
}

/** A 4x4 pose from R [3x3] and t [3]. */
export function compose(R, t) {
  return [[...R[0], t[0]], [...R[1], t[1]], [...R[2], t[2]], [0, 0, 0, 1]];
}

/** T_obj_cam of a camera at `eye` looking at `target` with `up` towards the image top; returns T_cam_obj. */
export function lookAt(eye, target, up = [0, 0, 1]) {
  const forward = normalize(sub(target, eye));
  let right = cross(forward, up);
  if (Math.hypot(...right) < 1e-9) right = cross(forward, [0, 1, 0]);
  right = normalize(right);
  const down = cross(forward, right);
  const R = [right, down, forward]; // rows: the camera axes in the object frame, i.e. R_cam_obj
  return compose(R, scale(apply(R, eye), -1));
}

/**
 * The orbit camera of the model view: at `distance` from `target`, `azimuth` about the object's z axis
 * and `elevation` above its xy plane (radians). Returns T_cam_obj.
 */
export function orbitPose({ target, azimuth, elevation, distance }) {
  const c = Math.cos(elevation);
  const eye = add(target, scale([c * Math.cos(azimuth), c * Math.sin(azimuth), Math.sin(elevation)], distance));
  return lookAt(eye, target);
}

/** Rotation [3x3] from roll, pitch, yaw (radians) in the ROS convention: R = Rz(yaw) Ry(pitch) Rx(roll). */
export function rpyToMatrix([roll, pitch, yaw]) {
  const [cr, sr, cp, sp, cy, sy] = [Math.cos(roll), Math.sin(roll), Math.cos(pitch), Math.sin(pitch), Math.cos(yaw), Math.sin(yaw)];
  return [
    [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
    [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
    [-sp, cp * sr, cp * cr],
  ];
}

/** [roll, pitch, yaw] (radians) of a rotation [3x3]; the inverse of rpyToMatrix. */
export function matrixToRpy(R) {
  const pitch = Math.asin(Math.max(-1, Math.min(1, -R[2][0])));
  if (Math.abs(R[2][0]) < 1 - 1e-9) return [Math.atan2(R[2][1], R[2][2]), pitch, Math.atan2(R[1][0], R[0][0])];
  return [0, pitch, Math.atan2(-R[0][1], R[1][1])]; // gimbal lock: roll folded into yaw
}

/** Rotation [3x3] of `angle` radians about the unit `axis`. */
export function axisAngle(axis, angle) {
  const [x, y, z] = normalize(axis);
  const c = Math.cos(angle), s = Math.sin(angle), C = 1 - c;
  return [
    [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
    [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
    [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
  ];
}

/** T_cam_obj rotated by Rd [3x3] (camera frame) about the camera-frame point `pivot` [3]. */
export function rotateAbout(T, Rd, pivot) {
  const { R, t } = split(T);
  return compose(matmul3(Rd, R), add(apply(Rd, sub(t, pivot)), pivot));
}

/** A pinhole K [3x3] for a `width` x `height` image with horizontal field of view `fovDeg`. */
export function intrinsics(width, height, fovDeg) {
  const f = width / 2 / Math.tan(radians(fovDeg) / 2);
  return [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]];
}

/** The centre [3] and half-diagonal (m) of an object-frame box [[xmin, ymin, zmin], [xmax, ymax, zmax]]. */
export function boxCentre(bounds) {
  const [lo, hi] = bounds;
  return { centre: scale(add(lo, hi), 0.5), radius: Math.hypot(...sub(hi, lo)) / 2 };
}

/** An object-frame point [3] in the camera frame. */
export function transformPoint(T, p) {
  const { R, t } = split(T);
  return add(apply(R, p), t);
}
