// The web console's 3D view: the arm, the probe, the patient's markers and the contact force, in the robot's
// base frame (z up, metres), drawn with three.js from the state the server pushes. Rendered only when something
// changed (a state, the user turning the view): a phone's GPU and battery are not spent on a still picture.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";

const FORCE_COLOURS = { green: 0x28be3c, yellow: 0xf0c814, red: 0xe62828, grey: 0x8c8c8c };
const N_PER_M = 100; // the force arrow: 1 N draws 1 cm

function rotvecToQuaternion(rx, ry, rz) {
  const angle = Math.hypot(rx, ry, rz);
  const q = new THREE.Quaternion();
  if (angle > 1e-12) q.setFromAxisAngle(new THREE.Vector3(rx / angle, ry / angle, rz / angle), angle);
  return q;
}

export function createViewer(canvas) {
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, powerPreference: "low-power" });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x10151c);
  const camera = new THREE.PerspectiveCamera(45, 1, 0.01, 20);
  camera.up.set(0, 0, 1);
  camera.position.set(0.75, -0.65, 0.55);
  const controls = new OrbitControls(camera, canvas);
  controls.target.set(0.22, 0, 0.18);
  controls.update();

  scene.add(new THREE.HemisphereLight(0xffffff, 0x334455, 2.2));
  const sun = new THREE.DirectionalLight(0xffffff, 1.4);
  sun.position.set(1, -1, 2);
  scene.add(sun);
  const grid = new THREE.GridHelper(1.6, 16, 0x3a4a5a, 0x24303c);
  grid.rotation.x = Math.PI / 2; // the XY plane: the robot's table
  scene.add(grid);
  scene.add(new THREE.AxesHelper(0.15)); // base frame: x red, y green, z blue

  const armMaterial = new THREE.MeshStandardMaterial({ color: 0x78a0d2, metalness: 0.2, roughness: 0.6 });
  const jointMaterial = new THREE.MeshStandardMaterial({ color: 0x3c5070 });
  const links = [];
  const joints = [];
  const unitCylinder = new THREE.CylinderGeometry(0.035, 0.035, 1, 16);
  const jointSphere = new THREE.SphereGeometry(0.045, 16, 12);
  for (let i = 0; i < 8; i++) {
    const link = new THREE.Mesh(unitCylinder, armMaterial);
    link.visible = false;
    scene.add(link);
    links.push(link);
  }
  for (let i = 0; i < 9; i++) {
    const joint = new THREE.Mesh(jointSphere, jointMaterial);
    joint.visible = false;
    scene.add(joint);
    joints.push(joint);
  }
  // The probe: along the tool's z axis from the TCP (drawn in a group placed at the TCP pose).
  const tool = new THREE.Group();
  const probe = new THREE.Mesh(new THREE.CylinderGeometry(0.012, 0.016, 0.08, 16),
    new THREE.MeshStandardMaterial({ color: 0xe8e8e8 }));
  probe.rotation.x = Math.PI / 2;
  probe.position.z = -0.04;
  tool.add(probe);
  tool.add(new THREE.AxesHelper(0.06));
  tool.visible = false;
  scene.add(tool);
  const arrow = new THREE.ArrowHelper(new THREE.Vector3(0, 0, 1), new THREE.Vector3(), 0.05, FORCE_COLOURS.grey);
  arrow.visible = false;
  scene.add(arrow);
  const markerGeometry = new THREE.PlaneGeometry(0.03, 0.03);
  const markerMaterial = new THREE.MeshBasicMaterial({ color: 0xf2f2f2, side: THREE.DoubleSide });
  const markers = new Map();

  const yAxis = new THREE.Vector3(0, 1, 0);
  let dirty = true;
  controls.addEventListener("change", () => { dirty = true; });

  function placeLink(mesh, a, b) {
    const from = new THREE.Vector3(...a);
    const dir = new THREE.Vector3(...b).sub(from);
    const length = dir.length();
    mesh.visible = length > 1e-4;
    if (!mesh.visible) return;
    mesh.scale.set(1, length, 1);
    mesh.quaternion.setFromUnitVectors(yAxis, dir.clone().normalize());
    mesh.position.copy(from.addScaledVector(dir, 0.5));
  }

  function update(state) {
    const arm = state.arm || null;
    for (let i = 0; i < links.length; i++) {
      if (arm && i + 1 < arm.length) placeLink(links[i], arm[i], arm[i + 1]);
      else links[i].visible = false;
    }
    joints.forEach((j, i) => {
      j.visible = !!(arm && i < arm.length);
      if (j.visible) j.position.set(...arm[i]);
    });
    if (state.tcp) {
      const [x, y, z, rx, ry, rz] = state.tcp;
      tool.position.set(x, y, z);
      tool.quaternion.copy(rotvecToQuaternion(rx, ry, rz));
      tool.visible = true;
      const f = state.force && state.force.vector;
      const magnitude = f ? Math.hypot(...f) : 0;
      arrow.visible = magnitude > 0.2;
      if (arrow.visible) {
        arrow.position.set(x, y, z);
        arrow.setDirection(new THREE.Vector3(f[0] / magnitude, f[1] / magnitude, f[2] / magnitude));
        arrow.setLength(Math.min(magnitude / N_PER_M, 0.3), 0.02, 0.012);
        arrow.setColor(FORCE_COLOURS[state.force.colour] || FORCE_COLOURS.grey);
      }
    }
    const seen = new Set();
    for (const m of state.markers || []) {
      seen.add(m.id);
      let mesh = markers.get(m.id);
      if (!mesh) {
        mesh = new THREE.Mesh(markerGeometry, markerMaterial);
        mesh.matrixAutoUpdate = false;
        scene.add(mesh);
        markers.set(m.id, mesh);
      }
      const p = m.pose; // 4x4 row-major
      mesh.matrix.set(p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7], p[8], p[9], p[10], p[11], p[12], p[13], p[14], p[15]);
      mesh.visible = true;
    }
    for (const [id, mesh] of markers) if (!seen.has(id)) mesh.visible = false;
    dirty = true;
  }

  function resize() {
    const w = canvas.clientWidth;
    const h = canvas.clientHeight;
    if (!w || !h) return;
    if (canvas.width !== Math.floor(w * renderer.getPixelRatio()) || canvas.height !== Math.floor(h * renderer.getPixelRatio())) {
      renderer.setSize(w, h, false);
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
      dirty = true;
    }
  }

  function frame() {
    resize();
    if (dirty) {
      renderer.render(scene, camera);
      dirty = false;
    }
    requestAnimationFrame(frame);
  }
  requestAnimationFrame(frame);
  // Fewer pixels a frame (the page's choice, when drawing makes it late): the next frame is drawn at that ratio.
  function setPixelRatio(ratio) {
    renderer.setPixelRatio(ratio);
    dirty = true;
  }
  return { update, setPixelRatio };
}
