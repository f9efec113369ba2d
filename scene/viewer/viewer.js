/* hackneck viewer: shows the rig's GLB posed frame by frame, from the embedded clip or from frames pushed by a
   live source, with tau and the joint angles drawn under it; window.hackneck is its interface to scripts.

   A frame: {time, frame, theta: [J][3] axis-angle (or flat J*3) | bones: {joint: [x, y, z, w]} relative to
   rest, psi: [E] | morphs: {expression: weight}, tau, eta}.  applyFrame(frame) poses the character;
   pushFrame(frame) also appends it to the curves (live).  The larynx morph weights (eta times hat weights of
   tau on the GLB's larynx targets) and the pose correctives ((R - I) entries of theta) are computed here as
   scene.gltf computes them.  With a companion (header.companion and a second GLB: the human beside the
   giraffe it drives), the companion stands to the left and plays its own clip on the same clock; state()
   reports it under "companion". */
(function () {
  'use strict';
  const { THREE, GLTFLoader, OrbitControls } = window.HACKNECK_THREE;
  const api = window.hackneck = { ready: false, error: null };
  const $ = (id) => document.getElementById(id);
  const statusBox = $('status');

  function fail(error) {
    api.error = String(error && error.stack || error);
    statusBox.textContent = 'error: ' + api.error;
    console.error(error);
  }

  function decode(b64, Type) {
    const bin = atob(b64);
    const bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return Type ? new Type(bytes.buffer) : bytes.buffer;
  }

  const header = JSON.parse($('hackneck-header').textContent);
  const joints = header.joints, J = joints.length;     // the main character's, for the curves

  // A clip (absent in live mode): typed arrays, frame-major.
  function readClip(spec) {
    if (!(spec.data && spec.frames > 0)) return null;
    const d = spec.data;
    return { time: decode(d.time, Float64Array), theta: decode(d.theta, Float32Array), psi: decode(d.psi, Float32Array),
             tau: decode(d.tau, Float32Array), eta: decode(d.eta, Float32Array), count: spec.frames };
  }
  const clip = readClip(header);

  // Curves: the clip's arrays, or a bounded history of pushed frames.
  const LIVE_SECONDS = 20, LIVE_MAX = 20000;
  const series = clip || { time: [], theta: [], psi: null, tau: [], eta: [], count: 0 };
  let plotDirty = true;

  // ---- the 3D scene ----
  const view = $('view');
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  view.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x1e2228);
  const camera = new THREE.PerspectiveCamera(30, 1, 0.001, 100);
  const controls = new OrbitControls(camera, renderer.domElement);
  controls.enableDamping = false;
  scene.add(new THREE.HemisphereLight(0xf4f6ff, 0x40362e, 1.6));
  const key = new THREE.DirectionalLight(0xffffff, 2.4);
  const fill = new THREE.DirectionalLight(0xdde6ff, 0.8);
  scene.add(key, fill, key.target, fill.target);

  function resize() {
    const w = Math.max(view.clientWidth, 1), h = Math.max(view.clientHeight, 1);
    renderer.setSize(w, h, false);
    camera.aspect = w / h;
    camera.updateProjectionMatrix();
    plotDirty = true;
  }
  new ResizeObserver(resize).observe(view);
  window.addEventListener('resize', resize);

  // ---- the characters: a puppet is one GLB's mesh and bones with the names and rest rotations of its spec ----
  function makePuppet(spec, gltf) {
    const p = { joints: spec.joints, expressions: spec.expressions, J: spec.joints.length, E: spec.expressions.length,
                rest: spec.rest.map((q) => new THREE.Quaternion(q[0], q[1], q[2], q[3])), clip: readClip(spec),
                root: gltf.scene, mesh: null, bones: [], larynx: [], correctives: [] };
    p.restInverse = p.rest.map((q) => q.clone().invert());
    p.current = { time: 0, frame: 0, tau: 0, eta: 0, theta: new Float64Array(p.J * 3), relative: p.rest.map(() => new THREE.Quaternion()) };
    let mesh = null;
    const root = gltf.scene;
    root.traverse((o) => {
      if (o.isMesh && o.morphTargetDictionary && !mesh) mesh = o;
      if (o.isMesh) {
        for (const m of Array.isArray(o.material) ? o.material : [o.material]) {
          if ('metalness' in m) m.metalness = 0;  // no environment map: metallic renders black
          if ('roughness' in m) m.roughness = Math.max(m.roughness, 0.55);
          m.side = THREE.DoubleSide;
        }
        o.frustumCulled = false;
      }
    });
    if (!mesh) throw new Error('the GLB holds no mesh with morph targets');
    p.mesh = mesh;
    p.bones = p.joints.map((name) => {
      const bone = root.getObjectByName(THREE.PropertyBinding.sanitizeNodeName(name));
      if (!bone) throw new Error('joint ' + name + ' is not in the GLB');
      return bone;
    });
    const names = Object.keys(mesh.morphTargetDictionary);
    const extras = (gltf.asset && gltf.asset.extras) || {};
    const larynxNames = names.filter((n) => n.startsWith('larynx_tau')).sort((a, b) =>
      mesh.morphTargetDictionary[a] - mesh.morphTargetDictionary[b]);
    const taus = extras.larynx_taus || larynxNames.map((n) => parseFloat(n.slice('larynx_tau'.length)));
    p.larynx = larynxNames.map((n, k) => ({ index: mesh.morphTargetDictionary[n], tau: taus[k] }));
    for (const n of names) {
      const m = /^corrective_(.+)_r(\d)c(\d)$/.exec(n);
      if (m) p.correctives.push({ index: mesh.morphTargetDictionary[n], joint: p.joints.indexOf(m[1]), r: +m[2], c: +m[3] });
    }
    scene.add(root);
    return p;
  }

  let main = null, companion = null;
  let current = { time: 0, frame: 0, tau: 0, eta: 0, theta: new Float64Array(J * 3) };   // main.current once loaded

  // The companion to the left of the main character, a fifth of their widths apart.
  function placeSideBySide() {
    main.root.updateMatrixWorld(true); companion.root.updateMatrixWorld(true);
    const a = new THREE.Box3().setFromObject(main.mesh), b = new THREE.Box3().setFromObject(companion.mesh);
    const gap = 0.2 * Math.max(a.max.x - a.min.x, b.max.x - b.min.x);
    companion.root.position.x += a.min.x - gap - b.max.x;
    companion.root.updateMatrixWorld(true);
  }

  function frame() {
    const box = new THREE.Box3();
    for (const p of companion ? [main, companion] : [main]) { p.root.updateMatrixWorld(true); box.expandByObject(p.mesh); }
    const size = box.getSize(new THREE.Vector3()), centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(size.length() / 2, 1e-3);
    const distance = radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.05;
    const direction = new THREE.Vector3(0.45, 0.12, 1).normalize();   // three-quarter, face towards +z
    camera.position.copy(centre).addScaledVector(direction, distance);
    camera.near = distance / 100; camera.far = distance * 100;
    camera.updateProjectionMatrix();
    controls.target.copy(centre);
    controls.update();
    key.position.copy(centre).add(new THREE.Vector3(1, 2, 2.5).multiplyScalar(radius));
    fill.position.copy(centre).add(new THREE.Vector3(-2, 0.3, 1).multiplyScalar(radius));
    key.target.position.copy(centre); fill.target.position.copy(centre);
  }

  function hatWeights(nodes, value) {
    const out = nodes.map(() => 0), K = nodes.length;
    if (K === 1) { out[0] = 1; return out; }
    const v = Math.min(Math.max(value, nodes[0]), nodes[K - 1]);
    let right = 0;
    while (right < K && nodes[right] <= v) right++;
    right = Math.min(Math.max(right, 1), K - 1);
    const left = right - 1, f = (v - nodes[left]) / (nodes[right] - nodes[left]);
    out[left] = 1 - f; out[right] += f;
    return out;
  }

  const axis = new THREE.Vector3(), rotation = new THREE.Matrix4();
  function applyFrame(f) {
    if (!main) return;
    posePuppet(main, f);
    updateClock();
  }

  function posePuppet(p, f) {
    const { mesh, bones, larynx, correctives, joints, rest, current, J, E, expressions } = p;
    const influences = mesh.morphTargetInfluences;
    for (let j = 0; j < J; j++) {
      const q = current.relative[j];
      let v = null;
      if (f.theta) v = Array.isArray(f.theta[0]) ? f.theta[j] : [f.theta[3 * j], f.theta[3 * j + 1], f.theta[3 * j + 2]];
      if (v) {
        const angle = Math.hypot(v[0], v[1], v[2]);
        if (angle > 1e-12) q.setFromAxisAngle(axis.set(v[0] / angle, v[1] / angle, v[2] / angle), angle);
        else q.identity();
        current.theta.set(v, 3 * j);
      } else if (f.bones && f.bones[joints[j]]) {
        const b = f.bones[joints[j]];
        q.set(b[0], b[1], b[2], b[3]).normalize();
        const w = Math.min(Math.abs(q.w), 1), angle = 2 * Math.acos(w), s = Math.sqrt(Math.max(1 - w * w, 0));
        const sign = q.w < 0 ? -1 : 1;
        for (let a = 0; a < 3; a++) current.theta[3 * j + a] = s > 1e-12 ? sign * [q.x, q.y, q.z][a] / s * angle : 0;
      }
      bones[j].quaternion.copy(rest[j]).multiply(q);
    }
    if (f.psi) for (let e = 0; e < E; e++) setMorph(mesh, expressions[e], f.psi[e]);
    else if (f.morphs) for (const name in f.morphs) setMorph(mesh, name, f.morphs[name]);
    if (f.tau !== undefined) current.tau = +f.tau;
    if (f.eta !== undefined) current.eta = +f.eta;
    if (larynx.length) {
      const w = hatWeights(larynx.map((l) => l.tau), current.tau);
      larynx.forEach((l, k) => { influences[l.index] = current.eta * w[k]; });
    }
    for (const c of correctives) {
      const e = rotation.makeRotationFromQuaternion(current.relative[c.joint]).elements;   // column-major
      influences[c.index] = e[c.c * 4 + c.r] - (c.r === c.c ? 1 : 0);
    }
    if (f.time !== undefined) current.time = +f.time;
    current.frame = f.frame !== undefined ? f.frame : current.frame + 1;
  }

  function setMorph(mesh, name, weight) {
    const index = mesh.morphTargetDictionary[name];
    if (index !== undefined) mesh.morphTargetInfluences[index] = +weight;
  }

  // ---- the clip's clock ----
  let playing = false, playTime = 0;
  const start = clip ? clip.time[0] : 0, end = clip ? clip.time[clip.count - 1] : 0;

  function clipFrame(clip, t) {
    const time = clip.time, n = clip.count, J = clip.theta.length / n, E = clip.psi.length / n;
    t = Math.min(Math.max(t, start), end);
    let lo = 0, hi = n - 1;                       // the last frame at or before t
    while (lo < hi) { const mid = (lo + hi + 1) >> 1; if (time[mid] <= t) lo = mid; else hi = mid - 1; }
    const i = lo, k = Math.min(i + 1, n - 1);
    const a = k > i ? (t - time[i]) / (time[k] - time[i]) : 0;
    const mix = (arr, width, c) => arr[i * width + c] * (1 - a) + arr[k * width + c] * a;
    const theta = new Array(J), psi = new Array(E);
    for (let c = 0; c < J; c++) theta[c] = a ? mix(clip.theta, J, c) : clip.theta[i * J + c];
    for (let c = 0; c < E; c++) psi[c] = a ? mix(clip.psi, E, c) : clip.psi[i * E + c];
    return { time: t, frame: i, theta, psi, tau: a ? mix(clip.tau, 1, 0) : clip.tau[i], eta: a ? mix(clip.eta, 1, 0) : clip.eta[i] };
  }

  function seek(seconds) {
    if (!clip) return api.state();
    playTime = Math.min(Math.max(+seconds, start), end);
    applyFrame(clipFrame(clip, playTime));
    if (companion && companion.clip) posePuppet(companion, clipFrame(companion.clip, playTime));
    return api.state();
  }

  // ---- live: frames pushed by a source ----
  function pushFrame(f) {
    applyFrame(f);
    if (clip) return;
    series.time.push(current.time); series.tau.push(current.tau); series.eta.push(current.eta);
    for (let c = 0; c < J * 3; c++) series.theta.push(current.theta[c]);
    series.count++;
    const old = series.count - LIVE_MAX;
    const cutoff = current.time - LIVE_SECONDS * 1.5;
    let drop = Math.max(old, 0);
    while (drop < series.count && series.time[drop] < cutoff) drop++;
    if (drop > 0) {
      series.time.splice(0, drop); series.tau.splice(0, drop); series.eta.splice(0, drop);
      series.theta.splice(0, drop * J * 3); series.count -= drop;
    }
    plotDirty = true;
  }

  // ---- live: frames from motion.live's server over a WebSocket (the page served over http) ----
  // Every phone seen is listed in the selector; the first is shown until another is chosen.
  let livePhone = null;
  const phoneSelect = $('phone');
  function selectPhone(phone) {
    if (phone === livePhone) return;
    livePhone = phone;
    phoneSelect.value = phone;
    series.time.length = 0; series.tau.length = 0; series.eta.length = 0; series.theta.length = 0;
    series.count = 0;
    plotDirty = true;
  }
  phoneSelect.addEventListener('change', () => selectPhone(phoneSelect.value));
  function notePhone(phone) {
    if ([...phoneSelect.options].some((o) => o.value === phone)) return;
    phoneSelect.add(new Option(phone, phone));
    phoneSelect.hidden = false;
    if (livePhone === null) selectPhone(phone);
  }
  function connectLive() {
    const socket = new WebSocket('ws://' + location.host + '/ws');
    socket.onopen = () => { statusBox.textContent = 'live: connected'; };
    socket.onmessage = (ev) => {
      try {
        const f = JSON.parse(ev.data);
        notePhone(f.phone);
        if (f.phone === livePhone) pushFrame(f);
      } catch (error) { console.error(error); }
    };
    socket.onclose = () => { statusBox.textContent = 'live: disconnected, retrying'; setTimeout(connectLive, 1000); };
  }

  // ---- controls ----
  const playButton = $('play'), scrub = $('scrub'), clock = $('clock');
  function setPlaying(on) {
    playing = !!on && !!clip;
    playButton.textContent = playing ? 'Pause' : 'Play';
  }
  function updateClock() {
    clock.textContent = current.time.toFixed(3) + ' s  ·  frame ' + current.frame + (clip ? ' / ' + (clip.count - 1) : '');
    if (clip && document.activeElement !== scrub) scrub.value = String(current.time);
  }
  playButton.addEventListener('click', () => setPlaying(!playing));
  scrub.addEventListener('input', () => { setPlaying(false); seek(parseFloat(scrub.value)); });
  window.addEventListener('keydown', (ev) => { if (ev.code === 'Space' && ev.target === document.body) { ev.preventDefault(); setPlaying(!playing); } });
  if (clip) { scrub.min = String(start); scrub.max = String(end); } else { scrub.disabled = true; playButton.disabled = true; }

  // ---- curves: tau (and eta), then flexion, axial rotation, lateral bend of each joint in degrees ----
  const plot = $('plot'), ctx = plot.getContext('2d');
  const colours = ['#e6194b', '#f58231', '#ffe119', '#bfef45', '#3cb44b', '#42d4f4', '#4363d8', '#f032e6', '#a9a9a9'];
  const strips = [
    { label: 'tau', values: (i) => [series.tau[i]], colours: ['#ffffff'] },
    { label: 'flexion (deg)', axis: 0 }, { label: 'axial rotation (deg)', axis: 1 }, { label: 'lateral bend (deg)', axis: 2 },
  ];
  let cache = null, xRange = [0, 1];

  function plotRange() {
    if (clip) return [start, Math.max(end, start + 1e-6)];
    const last = series.count ? series.time[series.count - 1] : 0;
    return [last - LIVE_SECONDS, last];
  }

  function drawCurves() {
    const w = plot.clientWidth || 1, h = plot.clientHeight || 1, dpr = window.devicePixelRatio || 1;
    if (!cache) cache = document.createElement('canvas');
    cache.width = plot.width = Math.round(w * dpr); cache.height = plot.height = Math.round(h * dpr);
    const g = cache.getContext('2d');
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.fillStyle = '#181b20'; g.fillRect(0, 0, w, h);
    xRange = plotRange();
    const left = 8, right = w - 8, stripH = h / strips.length;
    const x = (t) => left + (t - xRange[0]) / (xRange[1] - xRange[0]) * (right - left);
    const n = series.count;
    let first = 0;
    while (first < n && series.time[first] < xRange[0]) first++;
    strips.forEach((strip, s) => {
      const top = s * stripH + 14, bottom = (s + 1) * stripH - 4;
      const lines = strip.axis === undefined ? [(i) => series.tau[i]]
        : joints.map((_, j) => (i) => series.theta[(i * J + j) * 3 + strip.axis] * 180 / Math.PI);
      let lo = Infinity, hi = -Infinity;
      for (const f of lines) for (let i = first; i < n; i++) { const v = f(i); if (v < lo) lo = v; if (v > hi) hi = v; }
      if (!isFinite(lo)) { lo = -1; hi = 1; }
      const pad = Math.max((hi - lo) * 0.08, strip.axis === undefined ? 1e-4 : 0.5);
      lo -= pad; hi += pad;
      const y = (v) => bottom - (v - lo) / (hi - lo) * (bottom - top);
      g.strokeStyle = '#2c323b'; g.beginPath(); g.moveTo(left, bottom + 2); g.lineTo(right, bottom + 2); g.stroke();
      if (lo < 0 && hi > 0) { g.strokeStyle = '#3a414c'; g.beginPath(); g.moveTo(left, y(0)); g.lineTo(right, y(0)); g.stroke(); }
      lines.forEach((f, l) => {
        g.strokeStyle = strip.axis === undefined ? '#ffffff' : colours[l % colours.length];
        g.lineWidth = 1.2; g.beginPath();
        for (let i = first; i < n; i++) { const px = x(series.time[i]), py = y(f(i)); if (i === first) g.moveTo(px, py); else g.lineTo(px, py); }
        g.stroke();
      });
      g.fillStyle = '#aab3bf'; g.font = '11px system-ui, sans-serif';
      g.fillText(strip.label + '  [' + lo.toPrecision(3) + ', ' + hi.toPrecision(3) + ']', left + 2, s * stripH + 11);
    });
    g.font = '10px system-ui, sans-serif';
    joints.forEach((name, j) => { g.fillStyle = colours[j % colours.length]; g.fillText(name, right - 48 * (J - j), 11); });
    plotDirty = false;
  }

  function drawPlot() {
    if (plotDirty || !cache) drawCurves();
    const w = plot.clientWidth || 1, dpr = window.devicePixelRatio || 1;
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.drawImage(cache, 0, 0);
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    const px = 8 + (current.time - xRange[0]) / (xRange[1] - xRange[0]) * (w - 16);
    ctx.strokeStyle = '#ffd166'; ctx.lineWidth = 1.5;
    ctx.beginPath(); ctx.moveTo(px, 0); ctx.lineTo(px, plot.clientHeight); ctx.stroke();
  }

  function plotSeek(ev) {
    if (!clip) return;
    const r = plot.getBoundingClientRect();
    const t = xRange[0] + (ev.clientX - r.left - 8) / Math.max(r.width - 16, 1) * (xRange[1] - xRange[0]);
    setPlaying(false); seek(t);
  }
  plot.addEventListener('pointerdown', (ev) => { plotSeek(ev); plot.setPointerCapture(ev.pointerId); });
  plot.addEventListener('pointermove', (ev) => { if (ev.buttons & 1) plotSeek(ev); });
  window.addEventListener('resize', () => { plotDirty = true; });

  // ---- the loop ----
  let lastTick = performance.now();
  function tick(now) {
    const dt = Math.min(Math.max((now - lastTick) / 1000, 0), 0.25);
    lastTick = now;
    if (playing && clip) {
      let t = playTime + dt;
      if (t > end) t = end > start ? start + (t - end) % (end - start) : start;
      seek(t);
    }
    controls.update();
    renderer.render(scene, camera);
    drawPlot();
    requestAnimationFrame(tick);
  }

  // A puppet's last applied frame: each joint's rotation relative to rest (w >= 0) and the expressions' weights.
  function puppetState(p) {
    const c = p.current;
    const out = { time: c.time, frame: c.frame, bones: {}, morphs: {}, tau: c.tau, eta: c.eta };
    const q = new THREE.Quaternion();
    p.bones.forEach((bone, j) => {
      q.copy(p.restInverse[j]).multiply(bone.quaternion);
      if (q.w < 0) q.set(-q.x, -q.y, -q.z, -q.w);
      out.bones[p.joints[j]] = [q.x, q.y, q.z, q.w];
    });
    for (const name of p.expressions) {
      const index = p.mesh.morphTargetDictionary[name];
      if (index !== undefined) out.morphs[name] = p.mesh.morphTargetInfluences[index];
    }
    return out;
  }

  // ---- window.hackneck ----
  Object.assign(api, {
    header,
    state() {
      const out = main ? puppetState(main) : { time: 0, frame: 0, bones: {}, morphs: {}, tau: 0, eta: 0 };
      if (companion) out.companion = puppetState(companion);
      return out;
    },
    // The view as the last render drew it: column-major 4x4 matrices (three.js's order) taking the GLB's
    // world coordinates (metres, y up) to clip space, and the canvas size in CSS pixels.
    camera() {
      const canvas = renderer.domElement;
      return { projection: Array.from(camera.projectionMatrix.elements),
               view: Array.from(camera.matrixWorldInverse.elements),
               model: main ? Array.from(main.root.matrixWorld.elements) : null,
               companionModel: companion ? Array.from(companion.root.matrixWorld.elements) : null,
               width: canvas.clientWidth, height: canvas.clientHeight };
    },
    seek, applyFrame, pushFrame,
    phones: () => [...phoneSelect.options].map((o) => o.value),
    selectPhone,
    play() { setPlaying(true); },
    pause() { setPlaying(false); },
    playing: () => playing,
    duration: () => end - start,
  });

  try {
    const load = (id) => new Promise((resolve, reject) =>
      new GLTFLoader().parse(decode($(id).textContent.trim()), '', resolve, reject));
    const loads = [load('hackneck-glb')].concat(header.companion ? [load('hackneck-glb-companion')] : []);
    Promise.all(loads).then((gltfs) => {
      try {
        main = makePuppet(header, gltfs[0]);
        current = main.current;
        if (gltfs[1]) { companion = makePuppet(header.companion, gltfs[1]); placeSideBySide(); }
        frame();
        resize();
        if (clip) seek(start); else applyFrame({ time: 0, frame: 0 });
        setPlaying(clip !== null);
        statusBox.textContent = clip ? clip.count + ' frames at ' + header.fps + ' fps' : 'live';
        renderer.render(scene, camera);
        api.ready = true;
        requestAnimationFrame(tick);
        if (!clip && location.protocol === 'http:') connectLive();
      } catch (error) { fail(error); }
    }, fail);
  } catch (error) { fail(error); }
})();
