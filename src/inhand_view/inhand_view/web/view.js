// The live view's page: polls the node's /state.json and draws the map on a 2D canvas.
// Plain JavaScript, no library and no network but the node: it works offline, and without
// WebGL (headless browsers take reliable screenshots of it).
//
// URL parameters set the first view: frame=map|tracker,
// projection=orthographic|perspective, colour=texture|probability, threshold=0..0.95,
// explored=0|1, parts=0|1, uncertainty=0|1, up=auto|+z|-z.
'use strict';

(() => {
  const params = new URLSearchParams(window.location.search);
  const view = {
    frame: params.get('frame') || 'map',
    projection: params.get('projection') || 'orthographic',
    colour: params.get('colour') || 'texture',
    threshold: Number(params.get('threshold') || '0.6'),
    explored: params.get('explored') !== '0',
    parts: params.get('parts') !== '0',
    uncertainty: params.get('uncertainty') !== '0',
    up: params.get('up') || 'auto',
    yaw: -0.65, pitch: 0.5, zoom: 1, pan: [0, 0],
    target: [0, 0, 0], radius: 0.08, autoFit: true,
  };
  const FINGER_COLOURS = ['#38d7ff', '#d070ff', '#7ee03c', '#f2f2f2', '#8fa2ff'];
  const AXIS_COLOURS = ['#ff5a5a', '#4fd36b', '#5b8cff'];
  const EXPLORED_COLOUR = '#ffffff';
  // probability 0.5 -> 1: pale yellow, orange, red
  const STOPS = [[0, [250, 236, 130]], [0.4, [252, 176, 48]], [0.7, [236, 96, 24]], [1, [190, 22, 34]]];

  let state = null;          // the latest /state.json
  let map = null;            // its decoded map (kept across polls while unchanged)
  let shape = null;          // the shape node's parts and grasps, sent with the map
  let exploration = null;    // the exploration node's predicted surface and next touches
  let pollFailures = 0;
  let redrawPending = false;

  const $ = (id) => document.getElementById(id);
  const canvas = $('scene');
  const ctx = canvas.getContext('2d');

  // ---------------------------------------------------------------- colours
  function probabilityRgb(p) {
    if (p <= 0.5) return [120, 134, 156];
    const t = Math.min(1, (p - 0.5) / 0.5);
    for (let k = 1; k < STOPS.length; k++) {
      if (t <= STOPS[k][0]) {
        const [t0, c0] = STOPS[k - 1];
        const [t1, c1] = STOPS[k];
        const f = (t - t0) / (t1 - t0);
        return c0.map((v, i) => Math.round(v + f * (c1[i] - v)));
      }
    }
    return STOPS[STOPS.length - 1][1];
  }
  const css = (rgb) => `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`;
  const packedCss = (v) => css([(v >> 16) & 255, (v >> 8) & 255, v & 255]);

  function drawLegend() {
    const legend = $('legend');
    const g = legend.getContext('2d');
    g.clearRect(0, 0, legend.width, legend.height);
    const w = legend.width - 20;
    for (let x = 0; x < w; x++) {
      g.fillStyle = css(probabilityRgb(0.5 + 0.5 * (x + 0.5) / w));
      g.fillRect(10 + x, 2, 1, 14);
    }
    g.fillStyle = '#8b96a3';
    g.font = '11px system-ui, sans-serif';
    g.textAlign = 'left'; g.fillText('p 0.5', 10, 30);
    g.textAlign = 'center'; g.fillText('0.75', 10 + w / 2, 30);
    g.textAlign = 'right'; g.fillText('1.0', 10 + w, 30);
  }

  // ---------------------------------------------------------------- data
  function decodeMap(raw, unit) {
    const n = raw.probability.length;
    const position = new Float64Array(n * 3);
    for (let i = 0; i < n * 3; i++) position[i] = raw.position[i] * unit;
    return {
      n, position, resolution: raw.resolution,
      probability: Float32Array.from(raw.probability, (v) => v / 1000),
      hits: raw.hits, explored: raw.explored, colour: raw.colour,
    };
  }

  function poseOf(frame) {
    // the pose [R (9), t (3)] of `frame` in the view frame, or null
    const frames = state && state.frames && state.frames[view.frame];
    return frames && frames[frame] ? frames[frame] : null;
  }

  function applyPose(pose, p) {
    if (!pose) return p;
    return [pose[0] * p[0] + pose[1] * p[1] + pose[2] * p[2] + pose[9],
            pose[3] * p[0] + pose[4] * p[1] + pose[5] * p[2] + pose[10],
            pose[6] * p[0] + pose[7] * p[1] + pose[8] * p[2] + pose[11]];
  }

  // The map and the trails are in the map's frame (`object`): in the tracker's view they
  // move with that frame's latest pose.
  function mapPose() {
    if (view.frame === 'map' || !state) return null;
    return poseOf(state.frames.map_frame);
  }

  // ---------------------------------------------------------------- camera
  // Which way is up: +z in the object's frame (objects stand on their +z), -z in the
  // tracker's (polhemus_source: z points down), and in a map frame that is the tracker's
  // twin (static mode: the map frame's pose in the tracker frame is the identity).
  function upAxis() {
    if (view.up !== 'auto') return view.up === '-z' ? -1 : 1;
    if (view.frame === 'tracker') return -1;
    const pose = state && state.frames.tracker[state.frames.map_frame];
    const identity = [1, 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0];
    return pose && pose.every((v, i) => Math.abs(v - identity[i]) < 1e-9) ? -1 : 1;
  }

  function camera() {
    const w = canvas.width, h = canvas.height;
    const scale = view.zoom * Math.min(w, h) * 0.42 / view.radius;
    const cy = Math.cos(view.yaw), sy = Math.sin(view.yaw);
    const cp = Math.cos(view.pitch), sp = Math.sin(view.pitch);
    const flip = upAxis() < 0;
    const distance = 3.2 * view.radius / view.zoom;
    return {
      scale,
      project(p) {
        let x = p[0] - view.target[0], y = p[1] - view.target[1], z = p[2] - view.target[2];
        if (flip) { y = -y; z = -z; }
        const x1 = cy * x - sy * y, y1 = sy * x + cy * y;
        const depth = -y1 * cp + z * sp;         // towards the viewer
        const up = z * cp + y1 * sp;
        let k = 1;
        if (view.projection === 'perspective') {
          if (depth > 0.9 * distance) return null;
          k = distance / (distance - depth);
        }
        return [w / 2 + (x1 * scale + view.pan[0]) * k, h / 2 - (up * scale + view.pan[1]) * k,
                depth, k];
      },
    };
  }

  function fit() {
    const pose = mapPose();
    const pts = [];
    if (map && map.n) {
      let any = false;
      for (let i = 0; i < map.n; i++) {
        if (map.probability[i] > Math.max(view.threshold, 0.5)) { any = true; break; }
      }
      for (let i = 0; i < map.n; i++) {
        if (!any || map.probability[i] > Math.max(view.threshold, 0.5)) {
          pts.push(applyPose(pose, [map.position[3 * i], map.position[3 * i + 1], map.position[3 * i + 2]]));
        }
      }
    }
    if (!pts.length && state) {
      for (const finger of state.fingers) {
        for (let i = 0; i < finger.trail.length; i += 3) {
          pts.push(applyPose(pose, finger.trail.slice(i, i + 3).map((v) => v * state.settings.position_unit)));
        }
      }
    }
    if (!pts.length) { view.target = [0, 0, 0]; view.radius = 0.08; return; }
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const p of pts) for (let a = 0; a < 3; a++) { lo[a] = Math.min(lo[a], p[a]); hi[a] = Math.max(hi[a], p[a]); }
    view.target = lo.map((v, a) => (v + hi[a]) / 2);
    view.radius = Math.max(0.02, 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]));
    view.pan = [0, 0];
    view.zoom = 1;
  }

  // ---------------------------------------------------------------- drawing
  function redraw() {
    if (redrawPending) return;
    redrawPending = true;
    window.requestAnimationFrame(() => { redrawPending = false; draw(); });
  }

  function resize() {
    const ratio = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * ratio));
    const h = Math.max(1, Math.round(canvas.clientHeight * ratio));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
  }

  function draw() {
    resize();
    ctx.fillStyle = '#101418';
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    if (view.autoFit) fit();
    const cam = camera();
    drawCells(cam);
    drawShape(cam);
    drawExploration(cam);
    drawFrames(cam);
    drawTrails(cam);
    drawScaleBar(cam);
    if (!map || !map.n) {
      ctx.fillStyle = '#6b7682';
      ctx.font = `${14 * (window.devicePixelRatio || 1)}px system-ui, sans-serif`;
      ctx.textAlign = 'center';
      ctx.fillText(state ? 'no map yet: waiting for occupancy/cloud' : 'connecting to the node…',
                   canvas.width / 2, 40 * (window.devicePixelRatio || 1));
    }
  }

  function drawCells(cam) {
    if (!map || !map.n) return;
    const pose = mapPose();
    const cut = view.threshold;
    const items = [];
    for (let i = 0; i < map.n; i++) {
      if (map.probability[i] <= cut && !(cut < 0.5 && map.hits[i] > 0)) continue;
      const p = applyPose(pose, [map.position[3 * i], map.position[3 * i + 1], map.position[3 * i + 2]]);
      const s = cam.project(p);
      if (s) items.push([s[2], i, s]);
    }
    items.sort((a, b) => a[0] - b[0]);                 // far first
    const textured = view.colour === 'texture' && map.colour;
    for (const [, i, s] of items) {
      const size = Math.max(1.5, map.resolution * cam.scale * s[3]);
      ctx.fillStyle = textured && map.colour[i] >= 0 ? packedCss(map.colour[i])
        : css(probabilityRgb(map.probability[i]));
      ctx.fillRect(s[0] - size / 2, s[1] - size / 2, size, size);
      if (view.explored && map.explored[i]) {
        ctx.strokeStyle = EXPLORED_COLOUR;
        ctx.lineWidth = Math.max(1, size * 0.12);
        ctx.strokeRect(s[0] - size / 2, s[1] - size / 2, size, size);
      }
    }
  }

  // The shape node's parts (shape/parts, after an "Extract shape"): triangles back to
  // front, lit by how squarely they face the viewer; the grasps as segments on top.
  function drawShape(cam) {
    if (!state || !shape || !view.parts) return;
    const pose = mapPose();
    const unit = state.settings.position_unit;
    const triangles = [];
    const segments = [];
    for (const item of shape.items) {
      const p = item.points;
      const screen = [];
      for (let i = 0; i + 2 < p.length; i += 3) {
        screen.push(cam.project(applyPose(pose, [p[i] * unit, p[i + 1] * unit, p[i + 2] * unit])));
      }
      if (item.kind === 'triangles') {
        for (let t = 0; t + 2 < screen.length; t += 3) {
          const [a, b, c] = [screen[t], screen[t + 1], screen[t + 2]];
          if (!a || !b || !c) continue;
          const u = [b[0] - a[0], a[1] - b[1], (b[2] - a[2]) * cam.scale];
          const v = [c[0] - a[0], a[1] - c[1], (c[2] - a[2]) * cam.scale];
          const n = [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]];
          const facing = Math.abs(n[2]) / (Math.hypot(n[0], n[1], n[2]) || 1);
          triangles.push([(a[2] + b[2] + c[2]) / 3, a, b, c, item.rgba, 0.35 + 0.65 * facing]);
        }
      } else {
        for (let s = 0; s + 1 < screen.length; s += 2) {
          if (screen[s] && screen[s + 1]) segments.push([screen[s], screen[s + 1], item.rgba]);
        }
      }
    }
    triangles.sort((x, y) => x[0] - y[0]);            // far first
    for (const [, a, b, c, rgba, light] of triangles) {
      ctx.fillStyle = `rgba(${Math.round(rgba[0] * 255 * light)},${Math.round(rgba[1] * 255 * light)},`
        + `${Math.round(rgba[2] * 255 * light)},${rgba[3]})`;
      ctx.beginPath();
      ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.lineTo(c[0], c[1]);
      ctx.closePath();
      ctx.fill();
    }
    const ratio = window.devicePixelRatio || 1;
    for (const [a, b, rgba] of segments) {
      ctx.strokeStyle = css(rgba.slice(0, 3).map((c) => Math.round(c * 255)));
      ctx.lineWidth = 2 * ratio;
      ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
      for (const end of [a, b]) {
        ctx.beginPath(); ctx.arc(end[0], end[1], 3 * ratio, 0, 2 * Math.PI);
        ctx.fillStyle = ctx.strokeStyle; ctx.fill();
      }
    }
  }

  // The exploration node's predicted surface as a heat map of its standard deviation
  // (dark blue known, yellow 10 mm or more: a guess, the prediction's default signal_std) and
  // the next touches as red arrows onto it, the best one thicker. The stops are
  // touch_guidance.std_colours' (the node's surface marker and predict_surface's picture).
  const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
  function stdRgb(metres) {
    const x = Math.min(1, Math.max(0, metres / 0.01)) * (VIRIDIS.length - 1);
    const k = Math.min(VIRIDIS.length - 2, Math.floor(x));
    return VIRIDIS[k].map((v, i) => Math.round(v + (x - k) * (VIRIDIS[k + 1][i] - v)));
  }

  function drawExploration(cam) {
    if (!state || !exploration || !view.uncertainty) return;
    const pose = mapPose();
    const unit = state.settings.position_unit;
    const p = exploration.points;
    const ratio = window.devicePixelRatio || 1;
    const dots = [];
    for (let i = 0; i + 2 < p.length; i += 3) {
      const s = cam.project(applyPose(pose, [p[i] * unit, p[i + 1] * unit, p[i + 2] * unit]));
      if (s) dots.push([s[2], s, exploration.std_um[i / 3] * 1e-6]);
    }
    dots.sort((a, b) => a[0] - b[0]);                 // far first
    for (const [, s, std] of dots) {
      ctx.fillStyle = css(stdRgb(std));
      ctx.fillRect(s[0] - 1.5 * ratio, s[1] - 1.5 * ratio, 3 * ratio, 3 * ratio);
    }
    exploration.touches.forEach((arrow, rank) => {
      const [a, b] = [0, 3].map((k) => cam.project(applyPose(pose, [arrow[k] * unit,
        arrow[k + 1] * unit, arrow[k + 2] * unit])));
      if (!a || !b) return;
      ctx.strokeStyle = ctx.fillStyle = rank === 0 ? '#ff3030' : 'rgba(255,80,80,0.7)';
      ctx.lineWidth = (rank === 0 ? 3 : 2) * ratio;
      ctx.beginPath(); ctx.moveTo(a[0], a[1]); ctx.lineTo(b[0], b[1]); ctx.stroke();
      ctx.beginPath(); ctx.arc(b[0], b[1], (rank === 0 ? 4 : 3) * ratio, 0, 2 * Math.PI); ctx.fill();
    });
  }

  function drawAxes(cam, pose, length, label, labels) {
    const o = applyPose(pose, [0, 0, 0]);
    const so = cam.project(o);
    if (!so) return;
    const ratio = window.devicePixelRatio || 1;
    for (let a = 0; a < 3; a++) {
      const tip = [0, 0, 0]; tip[a] = length;
      const st = cam.project(applyPose(pose, tip));
      if (!st) continue;
      ctx.strokeStyle = AXIS_COLOURS[a];
      ctx.lineWidth = 2 * ratio;
      ctx.beginPath(); ctx.moveTo(so[0], so[1]); ctx.lineTo(st[0], st[1]); ctx.stroke();
    }
    ctx.fillStyle = '#c7d0da';
    ctx.font = `${11 * ratio}px system-ui, sans-serif`;
    ctx.textAlign = 'left';
    // frames at one place (a static map frame and the tracker's) get their labels stacked
    let y = so[1] - 4 * ratio;
    while (labels.some(([lx, ly]) => Math.abs(lx - so[0]) < 40 * ratio && Math.abs(ly - y) < 12 * ratio)) {
      y -= 13 * ratio;
    }
    labels.push([so[0], y]);
    ctx.fillText(label, so[0] + 4 * ratio, y);
  }

  function drawFrames(cam) {
    const frames = state && state.frames ? state.frames[view.frame] || {} : {};
    const names = Object.keys(frames);
    const labels = [];
    if (!names.length) {
      const own = state ? state.frames[`${view.frame}_frame`] : 'object';
      drawAxes(cam, null, 0.03, `${own} (no transforms yet)`, labels);
      return;
    }
    for (const name of names) {
      const big = name === state.frames.map_frame || name === state.frames.tracker_frame;
      drawAxes(cam, frames[name], big ? 0.03 : 0.012, name, labels);
    }
  }

  function drawTrails(cam) {
    if (!state) return;
    const pose = mapPose();
    const unit = state.settings.position_unit;
    const ratio = window.devicePixelRatio || 1;
    for (const finger of state.fingers) {
      const colour = FINGER_COLOURS[finger.index % FINGER_COLOURS.length];
      const pts = [];
      for (let i = 0; i < finger.trail.length; i += 3) {
        const s = cam.project(applyPose(pose, [finger.trail[i] * unit, finger.trail[i + 1] * unit,
                                               finger.trail[i + 2] * unit]));
        if (s) pts.push(s);
      }
      ctx.strokeStyle = colour;
      ctx.lineWidth = 1.5 * ratio;
      for (let i = 1; i < pts.length; i++) {
        ctx.globalAlpha = 0.15 + 0.85 * i / pts.length;      // older: fainter
        ctx.beginPath(); ctx.moveTo(pts[i - 1][0], pts[i - 1][1]); ctx.lineTo(pts[i][0], pts[i][1]); ctx.stroke();
      }
      ctx.globalAlpha = 1;
      const tip = cam.project(applyPose(pose, finger.tip.map((v) => v * unit)));
      if (!tip) continue;
      ctx.fillStyle = colour;
      ctx.beginPath(); ctx.arc(tip[0], tip[1], 5 * ratio, 0, 2 * Math.PI); ctx.fill();
      const frames = state.frames[view.frame] || {};
      if (Object.keys(frames).some((name) => name.endsWith(`fingertip_${finger.label}`))) continue;
      ctx.font = `${11 * ratio}px system-ui, sans-serif`;
      ctx.textAlign = 'left';
      ctx.fillText(finger.label, tip[0] + 8 * ratio, tip[1] + 4 * ratio);
    }
  }

  function drawScaleBar(cam) {
    const ratio = window.devicePixelRatio || 1;
    let length = 0.01;
    for (const candidate of [0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5]) {
      if (candidate * cam.scale <= 160 * ratio) length = candidate;
    }
    const x = 16 * ratio, y = canvas.height - 18 * ratio, w = length * cam.scale;
    ctx.strokeStyle = '#c7d0da';
    ctx.lineWidth = 2 * ratio;
    ctx.beginPath(); ctx.moveTo(x, y - 5 * ratio); ctx.lineTo(x, y); ctx.lineTo(x + w, y); ctx.lineTo(x + w, y - 5 * ratio); ctx.stroke();
    ctx.fillStyle = '#c7d0da';
    ctx.font = `${11 * ratio}px system-ui, sans-serif`;
    ctx.textAlign = 'left';
    const note = view.projection === 'perspective' ? ' at the centre' : '';
    ctx.fillText(`${length >= 0.01 ? length * 100 + ' cm' : length * 1000 + ' mm'}${note}`, x, y - 8 * ratio);
  }

  // ---------------------------------------------------------------- the panel
  function row(name, value) {
    const tr = document.createElement('tr');
    const a = document.createElement('td'); a.textContent = name;
    const b = document.createElement('td'); b.textContent = value;
    tr.append(a, b);
    return tr;
  }
  const number = (v) => (v === null || v === undefined ? '–' : Number(v).toLocaleString('en'));

  function updatePanel() {
    const c = state.counts;
    $('counts').replaceChildren(
      row('touched cells (occupancy/cloud)', number(c.cells)),
      row('cells with evidence (drawn from)', number(c.shown_cells)),
      row('occupied cells (occupancy/occupied)', number(c.occupied_cells)),
      row('cells hit by a fingertip', number(c.hit_cells)),
      row(`most explored (top ${Math.round(state.settings.explored_fraction * 100)} %)`,
          c.explored_cells ? `${number(c.explored_cells)} cells, ≥ ${number(c.explored_min_hits)} hits` : '–'),
      row('fingertip points', number(c.fingertip_points)),
      row('transforms received', number(c.transforms)),
      row('topics forwarded', number(c.topics)));

    const fingers = $('fingers');
    if (state.fingers.length) {
      fingers.replaceChildren(...state.fingers.map((f) => {
        const li = document.createElement('li');
        const dot = document.createElement('span');
        dot.className = 'swatch';
        dot.style.background = FINGER_COLOURS[f.index % FINGER_COLOURS.length];
        li.append(dot, `${f.label}: last ${state.settings.trail_seconds} s of path`);
        return li;
      }));
    }

    const rates = Object.entries(state.rates);
    $('rates').replaceChildren(...(rates.length ? rates.map(([topic, r]) => {
      const tr = row(topic, `${r.rate.toFixed(1)} Hz`);
      tr.lastChild.className = 'rate';
      tr.title = `${number(r.messages)} messages`;
      return tr;
    }) : [row('no messages yet', '')]));

    const diagnostics = $('diagnostics');
    if (state.diagnostics.length) {
      const names = ['OK', 'WARN', 'ERROR', 'STALE'];
      diagnostics.replaceChildren(...state.diagnostics.map((s) => {
        const details = document.createElement('details');
        details.open = true;
        const summary = document.createElement('summary');
        const level = document.createElement('span');
        level.className = `level level-${Math.min(3, s.level)}`;
        level.textContent = names[Math.min(3, s.level)];
        summary.append(level, `${s.name}: ${s.message}`);
        const table = document.createElement('table');
        table.className = 'values';
        table.replaceChildren(...s.values.map(([k, v]) => row(k, v)));
        details.append(summary, table);
        return details;
      }));
    }

    const fox = state.foxglove;
    if (fox && fox.port) {
      const host = window.location.hostname || '127.0.0.1';
      $('foxglove').innerHTML = `Open connection &rarr; Foxglove WebSocket &rarr; <code>ws://${host}:${fox.port}</code>`
        + `<br>frames on <code>${fox.frames}</code>; services ${fox.services.map((s) => `<code>${s}</code>`).join(', ')}`;
    }
    const services = { reset: 'occupancy/reset', save: 'occupancy/save', shape: 'shape/extract' };
    for (const [name, service] of Object.entries(services)) {
      const ok = state.services[name];
      $(name).disabled = !ok;
      $(name).title = ok ? service : `${service} is not offered (is its node running?)`;
    }
    const options = $('frame').options;
    options[0].textContent = `${state.frames.map_frame} (the map's frame)`;
    options[1].textContent = `${state.frames.tracker_frame} (the tracker's)`;
    options[1].disabled = !state.frames.tracker[state.frames.map_frame];
  }

  // ---------------------------------------------------------------- polling
  async function poll() {
    const since = map ? `?since=${state.map_version}` : '';
    try {
      const response = await fetch(`state.json${since}`, { cache: 'no-store' });
      if (!response.ok) throw new Error(`HTTP ${response.status}`);
      const next = await response.json();
      if (next.map) {
        map = decodeMap(next.map, next.settings.position_unit);
        shape = next.shape;
        exploration = next.exploration;
      }
      state = next;
      pollFailures = 0;
      $('status').className = '';
      $('status').textContent = `live · map version ${state.map_version} · ${number(state.counts.topics)} topics`;
      updatePanel();
      redraw();
    } catch (error) {
      pollFailures += 1;
      $('status').className = 'offline';
      $('status').textContent = `no answer from the node (${error.message}); retrying`;
    }
    const rate = state ? state.settings.page_rate : 2;
    window.setTimeout(poll, Math.min(5000, 1000 / rate * (1 + Math.min(pollFailures, 4))));
  }

  async function call(name) {
    const answer = $('answer');
    answer.className = '';
    answer.textContent = `${name}…`;
    try {
      const response = await fetch(`call/${name}`, { method: 'POST' });
      const result = await response.json();
      answer.className = result.success ? 'ok' : 'failed';
      answer.textContent = `${name}: ${result.message || (result.success ? 'done' : 'failed')}`;
    } catch (error) {
      answer.className = 'failed';
      answer.textContent = `${name}: ${error.message}`;
    }
  }

  // ---------------------------------------------------------------- controls
  function bindControls() {
    for (const id of ['frame', 'projection', 'colour', 'up']) {
      $(id).value = view[id];
      $(id).addEventListener('change', () => { view[id] = $(id).value; view.autoFit = true; redraw(); });
    }
    $('threshold').value = view.threshold;
    $('threshold-value').textContent = view.threshold.toFixed(2);
    $('threshold').addEventListener('input', () => {
      view.threshold = Number($('threshold').value);
      $('threshold-value').textContent = view.threshold.toFixed(2);
      redraw();
    });
    $('explored').checked = view.explored;
    $('explored').addEventListener('change', () => { view.explored = $('explored').checked; redraw(); });
    $('parts').checked = view.parts;
    $('parts').addEventListener('change', () => { view.parts = $('parts').checked; redraw(); });
    $('uncertainty').checked = view.uncertainty;
    $('uncertainty').addEventListener('change', () => { view.uncertainty = $('uncertainty').checked; redraw(); });
    $('fit').addEventListener('click', () => { view.autoFit = true; redraw(); });
    $('reset').addEventListener('click', () => call('reset'));
    $('save').addEventListener('click', () => call('save'));
    $('shape').addEventListener('click', () => call('shape'));

    let drag = null;
    canvas.addEventListener('pointerdown', (e) => {
      drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey };
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener('pointermove', (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      view.autoFit = false;
      if (drag.pan) {
        const ratio = window.devicePixelRatio || 1;
        view.pan[0] += dx * ratio; view.pan[1] -= dy * ratio;
      } else {
        view.yaw += dx * 0.01;
        view.pitch = Math.max(-1.55, Math.min(1.55, view.pitch + dy * 0.01));
      }
      redraw();
    });
    canvas.addEventListener('pointerup', () => { drag = null; });
    canvas.addEventListener('wheel', (e) => {
      e.preventDefault();
      view.autoFit = false;
      view.zoom *= Math.exp(-e.deltaY * 0.0015);
      redraw();
    }, { passive: false });
    canvas.addEventListener('dblclick', () => { view.autoFit = true; redraw(); });
    window.addEventListener('resize', redraw);
  }

  drawLegend();
  bindControls();
  redraw();
  poll();
})();
