// Pose geometry shared by the viewer and the AR page: poses are COLMAP's cam_from_world
// (rotation as a unit quaternion [w, x, y, z], translation t).

// row-major 3×3 rotation of a unit quaternion
export function rotation([w, x, y, z]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

// world point of camera point p: Rᵀ (p − t)
export function toWorld(R, t, p) {
  const d = [p[0] - t[0], p[1] - t[1], p[2] - t[2]];
  return directionToWorld(R, d);
}

// world direction of camera direction d: Rᵀ d
export function directionToWorld(R, d) {
  return [0, 1, 2].map((j) => R[0][j] * d[0] + R[1][j] * d[1] + R[2][j] * d[2]);
}
