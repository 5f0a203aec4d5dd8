// The capture page's 3D view: the scan's points and the conformed mesh overlaid (three.js,
// Debian's libjs-three), the mesh coloured by each vertex's distance to the scan, the
// template's landmarks and every measurement drawn where it was taken, with its value.
// It renders only when something changed, so a 100k-point scan stays light. An operator
// may place the template's landmarks on the scan (pick a name, click the scan) and have
// the capture fitted again by them. The state is left on the container (data-state,
// counts) and in window.conformdViewer, whose calls the page's own buttons use too.
(function () {
  "use strict";
  const box = document.getElementById("viewer");
  if (!box) return;
  const id = box.dataset.capture;
  const fail = (why) => {
    box.dataset.state = "error";
    box.textContent = "3D view unavailable: " + why;
  };
  if (typeof THREE === "undefined" || !THREE.OrbitControls || !THREE.PLYLoader) {
    fail("three.js is not served (install Debian's libjs-three on the station)");
    return;
  }
  // the same viridis-like stops as the station's preview images
  const STOPS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
  function colourMap(t) {
    t = Math.min(Math.max(isFinite(t) ? t : 0, 0), 1) * 4;
    const i = Math.min(Math.floor(t), 3), f = t - i;
    return STOPS[i].map((c, k) => (c * (1 - f) + STOPS[i + 1][k] * f) / 255);
  }

  // points drawn while the view moves: software WebGL draws about a million points a
  // second (benches/viewer.rs), so a moving view keeps ~10-15 frames a second even there
  const MOVING_POINTS = 30000;
  // every k-th point of a cloud, as a geometry of its own
  function strided(geo, k) {
    const src = geo.attributes.position.array, m = Math.floor(src.length / 3 / k);
    const out = new Float32Array(3 * m);
    for (let i = 0; i < m; i++) out.set(src.subarray(3 * i * k, 3 * i * k + 3), 3 * i);
    const g = new THREE.BufferGeometry();
    g.setAttribute("position", new THREE.BufferAttribute(out, 3));
    return g;
  }

  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  const width = () => box.clientWidth || 800, height = () => box.clientHeight || 520;
  renderer.setSize(width(), height());
  box.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0xf4f4f4);
  const camera = new THREE.PerspectiveCamera(40, width() / height(), 0.001, 1000);
  camera.up.set(0, 0, 1); // the station's z is up
  scene.add(new THREE.HemisphereLight(0xffffff, 0x666666, 0.9));
  const sun = new THREE.DirectionalLight(0xffffff, 0.5);
  scene.add(sun);
  const controls = new THREE.OrbitControls(camera, renderer.domElement);
  let queued = false;
  const render = () => {
    if (queued) return;
    queued = true;
    requestAnimationFrame(() => {
      queued = false;
      sun.position.copy(camera.position);
      renderer.render(scene, camera);
    });
  };
  controls.addEventListener("change", render);
  window.addEventListener("resize", () => {
    camera.aspect = width() / height();
    camera.updateProjectionMatrix();
    renderer.setSize(width(), height());
    render();
  });

  const layers = { scan: [], mesh: [], landmarks: [], measurements: [], names: [] };
  const state = { scene: scene, scan: null, mesh: null, landmarks: [], measurements: [], render: render };
  window.conformdViewer = state;

  function label(text, colour, at, size, layer) {
    const c = document.createElement("canvas");
    const g = c.getContext("2d");
    const font = "28px sans-serif";
    g.font = font;
    c.width = Math.ceil(g.measureText(text).width) + 16;
    c.height = 40;
    g.font = font;
    g.fillStyle = "rgba(255,255,255,0.85)";
    g.fillRect(0, 0, c.width, c.height);
    g.fillStyle = colour;
    g.fillText(text, 8, 29);
    const tex = new THREE.CanvasTexture(c);
    const s = new THREE.Sprite(new THREE.SpriteMaterial({ map: tex, depthTest: false, sizeAttenuation: false }));
    s.scale.set(size * c.width / c.height, size, 1);
    s.position.copy(at);
    s.renderOrder = 10;
    if (layer) layers[layer].push(s);
    return s;
  }

  const get = (file, type) => fetch("/api/captures/" + encodeURIComponent(id) + "/" + file).then((r) => {
    if (!r.ok) throw new Error(file + ": HTTP " + r.status);
    return type === "json" ? r.json() : r.arrayBuffer();
  });
  const view = get("view.json", "json").catch(() => null); // older results have none
  Promise.all([get("scan.ply"), get("conformed.ply"), view]).then(([scanBytes, meshBytes, v]) => {
    const loader = new THREE.PLYLoader();
    const scanGeo = loader.parse(scanBytes);
    const meshGeo = loader.parse(meshBytes);
    meshGeo.computeBoundingSphere();
    const sphere = meshGeo.boundingSphere;
    const r = sphere.radius || 1;

    const points = new THREE.Points(scanGeo, new THREE.PointsMaterial({
      color: 0x222222, size: 1.5, sizeAttenuation: false, transparent: true, opacity: 0.35, depthWrite: false,
    }));
    points.name = "scan";
    scene.add(points);
    layers.scan.push(points);
    state.scan = points;

    const n = meshGeo.attributes.position.count;
    const dist = v && v.distance && v.distance.length === n ? v.distance : null;
    let top = 0;
    if (dist) {
      // the colour bar ends at the 98th percentile, so one far vertex does not grey the rest
      const sorted = Array.from(dist).filter(isFinite).sort((a, b) => a - b);
      top = sorted.length ? sorted[Math.floor(0.98 * (sorted.length - 1))] : 0;
      const colours = new Float32Array(3 * n);
      for (let i = 0; i < n; i++) colours.set(colourMap(top > 0 ? dist[i] / top : 0), 3 * i);
      meshGeo.setAttribute("color", new THREE.BufferAttribute(colours, 3));
    }
    meshGeo.computeVertexNormals();
    const mesh = new THREE.Mesh(meshGeo, new THREE.MeshLambertMaterial({
      color: dist ? 0xffffff : 0xc9a27e,
      vertexColors: dist ? THREE.VertexColors : THREE.NoColors,
      side: THREE.DoubleSide,
    }));
    mesh.name = "conformed";
    scene.add(mesh);
    layers.mesh.push(mesh);
    state.mesh = mesh;
    const bar = document.getElementById("viewer-bar");
    if (bar && dist) {
      const unit = v.unit === "m" ? 1000 : 1, name = v.unit === "m" ? "mm" : v.unit;
      bar.querySelector(".hi").textContent = (top * unit).toFixed(1) + " " + name;
      bar.querySelector(".lo").textContent = "0 " + name;
      bar.style.display = "";
    }

    const dot = new THREE.SphereBufferGeometry(r * 0.012, 12, 8);
    const dotMat = new THREE.MeshBasicMaterial({ color: 0xd0021b });
    for (const l of (v && v.landmarks) || []) {
      const g = new THREE.Group();
      g.name = "landmark:" + l.name;
      const at = new THREE.Vector3().fromArray(l.position);
      const m = new THREE.Mesh(dot, dotMat);
      m.position.copy(at);
      g.add(m);
      g.add(label(l.name, "#b00020", at.clone().add(new THREE.Vector3(0, 0, r * 0.03)), 0.03, "names"));
      g.userData = l;
      scene.add(g);
      layers.landmarks.push(g);
      state.landmarks.push(g);
    }

    const lineMat = new THREE.LineBasicMaterial({ color: 0x1f4fb4, depthTest: false });
    let unplaced = 0;
    for (const m of (v && v.measurements) || []) {
      const g = new THREE.Group();
      g.name = "measurement:" + m.name;
      g.userData = m;
      const unit = m.unit === "m" ? [100, "cm"] : [1, m.unit];
      const text = m.name + " " + (m.value * unit[0]).toFixed(1) + " " + unit[1];
      let anchor = null;
      for (const l of m.lines) {
        const pts = l.map((p) => new THREE.Vector3().fromArray(p));
        if (pts.length < 2) continue;
        const geo = new THREE.BufferGeometry().setFromPoints(pts);
        const line = m.closed ? new THREE.LineLoop(geo, lineMat) : new THREE.Line(geo, lineMat);
        line.renderOrder = 5;
        g.add(line);
        if (!anchor) {
          // a loop is labelled at its highest point, a line at its middle
          anchor = m.closed ? pts.reduce((a, b) => (b.z > a.z ? b : a)) : pts[Math.floor(pts.length / 2)];
        }
      }
      if (!anchor) {
        // areas and volumes: stacked above the subject
        anchor = sphere.center.clone().add(new THREE.Vector3(0, 0, r * (1.05 + 0.12 * unplaced++)));
      }
      g.add(label(text, "#1f4fb4", anchor, 0.035));
      scene.add(g);
      layers.measurements.push(g);
      state.measurements.push(g);
    }

    // while the view moves, a large scan is drawn by every k-th point (at most
    // MOVING_POINTS), whole again once it stops; the full cloud keeps its order, which the
    // rasteriser draws fastest
    const count = scanGeo.attributes.position.count;
    const few = count > MOVING_POINTS ? new THREE.Points(strided(scanGeo, Math.ceil(count / MOVING_POINTS)), points.material) : null;
    if (few) {
      few.visible = false;
      scene.add(few);
    }
    const lod = (moving) => {
      if (!few) return;
      const shown = points.visible || few.visible;
      few.visible = moving && shown;
      points.visible = !moving && shown;
    };
    controls.addEventListener("start", () => lod(true));
    controls.addEventListener("end", () => { lod(false); render(); });

    camera.position.copy(sphere.center).add(new THREE.Vector3(1.2 * r, -1.8 * r, 0.9 * r));
    camera.near = r / 100;
    camera.far = r * 100;
    camera.updateProjectionMatrix();
    controls.target.copy(sphere.center);
    controls.update();

    for (const input of document.querySelectorAll("#viewer-controls input[data-layer]")) {
      const show = () => {
        for (const o of layers[input.dataset.layer]) o.visible = input.checked;
        render();
      };
      input.addEventListener("change", show);
      show();
    }
    placing(v, r, points);
    box.dataset.scanPoints = scanGeo.attributes.position.count;
    box.dataset.meshVertices = n;
    box.dataset.landmarks = state.landmarks.length;
    box.dataset.measurements = state.measurements.length;
    // since the page was asked for: what the viewer benchmark reports
    box.dataset.loadMs = Math.round(performance.now());
    // the three.js objects and the moving-view switch, for a script that drives the
    // view (the viewer benchmark turns the camera and times frames with them)
    state.three = { renderer, scene, camera, controls, moving: lod, render };
    box.dataset.state = "ready";
    render();
  }).catch((e) => fail(e.message));

  // Landmark placing: a list of the template's landmark names beside the view; the
  // selected name goes where the scan is clicked (a click, not the end of a drag).
  function placing(v, r, points) {
    const panel = document.getElementById("landmarks-panel");
    const names = ((v && v.landmarks) || []).map((l) => l.name);
    if (!panel || !names.length) return;
    const placed = new Map(); // name -> {position, marker}
    const dot = new THREE.SphereBufferGeometry(r * 0.014, 12, 8);
    const mat = new THREE.MeshBasicMaterial({ color: 0x0a8f3c, depthTest: false });
    let selected = null;
    const list = panel.querySelector("#landmark-list");
    const said = panel.querySelector("#landmarks-said");
    const items = new Map();
    for (const name of names) {
      const li = document.createElement("li");
      li.dataset.name = name;
      const b = document.createElement("button");
      b.type = "button";
      b.textContent = name;
      b.onclick = () => select(name);
      const where = document.createElement("span");
      where.className = "where";
      where.textContent = " not placed";
      li.append(b, where);
      list.appendChild(li);
      items.set(name, li);
    }
    function show() {
      for (const [name, li] of items) {
        const p = placed.get(name);
        li.querySelector(".where").textContent = p
          ? " placed at (" + p.position.map((c) => c.toFixed(3)).join(", ") + ")"
          : " not placed";
        li.style.fontWeight = name === selected ? "bold" : "";
      }
      panel.dataset.placed = placed.size;
      render();
    }
    function select(name) {
      if (!items.has(name)) throw new Error("'" + name + "' is not one of the template's landmarks");
      selected = name;
      show();
    }
    function place(name, position) {
      if (!items.has(name)) throw new Error("'" + name + "' is not one of the template's landmarks");
      const old = placed.get(name);
      if (old) scene.remove(old.marker);
      const marker = new THREE.Mesh(dot, mat);
      marker.renderOrder = 20;
      marker.name = "placed:" + name;
      marker.position.fromArray(position);
      scene.add(marker);
      placed.set(name, { position: Array.from(position), marker: marker });
      // the next unplaced name is selected, so a round of clicks places them in order
      selected = names.find((n) => !placed.has(n)) || null;
      show();
    }
    function unplace(name) {
      const old = placed.get(name);
      if (old) scene.remove(old.marker);
      placed.delete(name);
      show();
    }
    // the scan point under a point of the canvas (client coordinates), or null
    const ray = new THREE.Raycaster();
    ray.params.Points.threshold = r * 0.01;
    function pickAt(x, y) {
      const rect = renderer.domElement.getBoundingClientRect();
      const ndc = new THREE.Vector2(((x - rect.left) / rect.width) * 2 - 1, -((y - rect.top) / rect.height) * 2 + 1);
      ray.setFromCamera(ndc, camera);
      // while the pointer is down the view shows the thinned cloud and hides this one,
      // and three.js skips hidden objects: a click's own press hid it
      const shown = points.visible;
      points.visible = true;
      const hit = ray.intersectObject(points)[0];
      points.visible = shown;
      if (!hit) return null;
      const a = points.geometry.attributes.position;
      return [a.getX(hit.index), a.getY(hit.index), a.getZ(hit.index)];
    }
    function clickAt(x, y) {
      if (!selected) return null;
      const p = pickAt(x, y);
      if (p) place(selected, p);
      return p;
    }
    let down = null;
    renderer.domElement.addEventListener("pointerdown", (e) => { down = [e.clientX, e.clientY]; });
    renderer.domElement.addEventListener("pointerup", (e) => {
      if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4 && e.button === 0) clickAt(e.clientX, e.clientY);
      down = null;
    });
    function submit(token) {
      const body = { landmarks: Array.from(placed, ([name, p]) => ({ name: name, position: p.position })) };
      const h = { "Content-Type": "application/json" };
      if (token) h.Authorization = "Bearer " + token;
      return fetch("/api/captures/" + encodeURIComponent(id) + "/landmarks", {
        method: "POST", headers: h, body: JSON.stringify(body),
      }).then((r) => r.json().then((j) => {
        said.textContent = r.ok ? "queued: the capture is fitted again with " + j.landmarks + " landmarks" : j.error;
        return { status: r.status, body: j };
      }));
    }
    panel.querySelector("#landmarks-submit").onclick = () => submit(panel.querySelector("#landmarks-token").value);
    panel.querySelector("#landmarks-clear").onclick = () => { for (const n of names) unplace(n); };
    Object.assign(state, {
      landmarkNames: names, select: select, place: place, unplace: unplace, pickAt: pickAt, clickAt: clickAt,
      placed: () => Array.from(placed, ([name, p]) => ({ name: name, position: p.position })),
      submitLandmarks: submit,
    });
    // landmarks placed earlier for this capture are shown to start from
    fetch("/api/captures/" + encodeURIComponent(id)).then((r) => r.json()).then((d) => {
      for (const l of d.placed_landmarks || []) if (items.has(l.name) && !placed.has(l.name)) place(l.name, l.position);
      panel.dataset.state = "ready";
    }).catch(() => { panel.dataset.state = "ready"; });
    select(names[0]);
  }
})();
