// A scripted Foxglove WebSocket client built only from Foxglove's own npm libraries
// (@foxglove/ws-protocol, @foxglove/rosmsg, @foxglove/rosmsg2-serialization) and ws.
// Usage: node client.mjs '<plan JSON>'; prints one JSON object per line on stdout.
// plan: {url, topics: [full topic names], count, timeoutMs, getParameters: [names],
//        setParameters: [[{name, value, type?}], ...], services: [names], stallMs, listOnly,
//        quiet (decode every message, print none),
//        subprotocols: [names offered in the WebSocket handshake] (default: both names, as the Foxglove app),
//        expectRefusal (the server is expected to refuse the handshake: print its HTTP status and body),
//        subscribeParameters: [names] (subscribe to their updates), awaitBefore / awaitAfter:
//        [{name, value}] (pushed updates to wait for before / after setParameters), watchMs (then print
//        every pushed update: parameterValues without a request id),
//        scripts: [{source, namespace}] (Foxglove user scripts of a layout: each is transpiled with the
//        TypeScript compiler and run on the first `count` messages of its inputs, as a viewer would)}
import { createRequire } from "node:module";
// the libraries are CommonJS packages
const require = createRequire(import.meta.url);
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { parse } = require("@foxglove/rosmsg");
const { MessageReader } = require("@foxglove/rosmsg2-serialization");
const WebSocket = require("ws");

const plan = JSON.parse(process.argv[2]);
const timeoutMs = plan.timeoutMs ?? 20000;
const out = (obj) =>
  process.stdout.write(
    JSON.stringify(obj, (_k, v) =>
      typeof v === "bigint" ? Number(v) : ArrayBuffer.isView(v) && !(v instanceof DataView) ? Array.from(v) : v,
    ) + "\n",
  );
// exit once everything written has reached the pipe (process.exit alone would cut it off)
const finish = (code) => process.stdout.write("", () => process.exit(code));
const fail = (text) => {
  out({ event: "error", text });
  finish(2);
};
setTimeout(() => fail(`timed out after ${timeoutMs} ms`), timeoutMs).unref?.();

// the Foxglove app offers both names of the protocol; foxglove-sdk servers accept foxglove.sdk.v1
const ws = new WebSocket(plan.url, plan.subprotocols ?? ["foxglove.sdk.v1", FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
if (plan.expectRefusal) {
  // with this listener `ws` reports the refused upgrade here instead of as an error
  ws.on("unexpected-response", (req, res) => {
    let body = "";
    res.on("data", (d) => (body += d));
    res.on("end", () => {
      out({ event: "refused", status: res.statusCode, body });
      req.destroy();
      finish(0);
    });
  });
}
const client = new FoxgloveClient({ ws });
const channels = new Map(); // topic -> channel
const services = new Map(); // name -> service
const waiters = [];
const statuses = [];
const notify = () => {
  for (const w of [...waiters]) {
    if (w.test()) {
      waiters.splice(waiters.indexOf(w), 1);
      w.resolve();
    }
  }
};
const until = (test) => (test() ? Promise.resolve() : new Promise((resolve) => waiters.push({ test, resolve })));
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

client.on("error", (e) => fail(String(e?.message ?? e)));
client.on("advertise", (list) => {
  for (const c of list) channels.set(c.topic, c);
  notify();
});
client.on("advertiseServices", (list) => {
  for (const s of list) services.set(s.name, s);
  notify();
});
client.on("status", (s) => {
  statuses.push(s);
  out({ event: "status", level: s.level, message: s.message });
  notify();
});
const parameterReplies = new Map();
const pushes = []; // parameter updates the server pushed (no request id), in arrival order
client.on("parameterValues", (m) => {
  if (m.id === undefined) pushes.push(...m.parameters.map((p) => ({ name: p.name, value: p.value })));
  else parameterReplies.set(m.id, m.parameters);
  notify();
});
const pushed = (list) => (list ?? []).every((w) => pushes.some((p) => p.name === w.name && p.value === w.value));
const serviceReplies = new Map();
client.on("serviceCallResponse", (m) => {
  serviceReplies.set(m.callId, { ok: true, m });
  notify();
});
client.on("serviceCallFailure", (m) => {
  serviceReplies.set(m.callId, { ok: false, message: m.message });
  notify();
});

const readers = new Map();
const received = new Map(); // topic -> count
const kept = new Map(); // topic -> the first `count` decoded messages (for plan.scripts)
const bySub = new Map(); // subscription id -> channel
const decoder = new TextDecoder();
function decode(channel, data) {
  if (channel.encoding === "json") return JSON.parse(decoder.decode(data));
  if (channel.encoding === "cdr" && channel.schemaEncoding === "ros2msg") {
    let reader = readers.get(channel.id);
    if (!reader) {
      reader = new MessageReader(parse(channel.schema, { ros2: true }));
      readers.set(channel.id, reader);
    }
    return reader.readMessage(data);
  }
  throw new Error(`cannot decode ${channel.topic}: ${channel.encoding}/${channel.schemaEncoding}`);
}
client.on("message", ({ subscriptionId, timestamp, data }) => {
  const channel = bySub.get(subscriptionId);
  if (!channel) return;
  const n = (received.get(channel.topic) ?? 0) + 1;
  received.set(channel.topic, n);
  if (plan.stallMs) return;
  if (plan.quiet) {
    decode(channel, new Uint8Array(data.buffer, data.byteOffset, data.byteLength)); // as a viewer would
  } else if (n <= (plan.count ?? 1)) {
    const value = decode(channel, new Uint8Array(data.buffer, data.byteOffset, data.byteLength));
    if (plan.scripts) {
      if (!kept.has(channel.topic)) kept.set(channel.topic, []);
      kept.get(channel.topic).push({ receiveTime: timestamp, value });
    } else {
      out({ event: "message", topic: channel.topic, schemaName: channel.schemaName, logTime: timestamp, value });
    }
  }
  notify();
});

await until(() => ws.readyState === WebSocket.OPEN);
if (plan.expectRefusal) fail(`the server accepted the handshake (subprotocol ${ws.protocol})`);
client.on("open", notify);
const topics = plan.topics ?? [];
await until(() => topics.every((t) => channels.has(t)) && (plan.services ?? []).every((s) => services.has(s)));
out({ event: "channels", protocol: ws.protocol, channels: [...channels.values()].map((c) => ({ topic: c.topic, encoding: c.encoding,
      schemaName: c.schemaName, schemaEncoding: c.schemaEncoding })),
      services: [...services.values()].map((s) => ({ name: s.name, type: s.type })) });

if (plan.listOnly) {
  out({ event: "done" });
  await new Promise(() => finish(0));
}
for (const t of topics) bySub.set(client.subscribe(channels.get(t).id), channels.get(t));
if (plan.stallMs) {
  // a viewer that stops reading: the TCP socket is no longer read, the server's queue fills
  await sleep(500);
  ws._socket.pause();
  out({ event: "stalled" });
  await sleep(plan.stallMs);
  out({ event: "done" });
  await new Promise(() => finish(0));
}
await until(() => topics.every((t) => (received.get(t) ?? 0) >= (plan.count ?? 1)));

const ts = plan.scripts ? require("typescript") : undefined;
for (const { source, namespace } of plan.scripts ?? []) {
  // what Foxglove does with a layout's user script: compile the TypeScript, call the default export
  // with {topic, receiveTime, message} for each message on its inputs, publish the result on `output`
  const js = ts.transpileModule(source, {
    compilerOptions: { module: ts.ModuleKind.ESNext, target: ts.ScriptTarget.ES2022 },
  }).outputText;
  const script = await import("data:text/javascript;base64," + Buffer.from(js).toString("base64"));
  for (const input of script.inputs) {
    for (const { receiveTime, value } of kept.get(namespace + input) ?? []) {
      const result = script.default({ topic: input, receiveTime, message: value });
      out({ event: "script", output: script.output, input, value, result });
    }
  }
}

if (plan.subscribeParameters) {
  client.subscribeParameterUpdates(plan.subscribeParameters);
  // the server handles a client's messages in order: once this is answered, the subscription holds
  client.getParameters(plan.subscribeParameters, "subscribed");
  await until(() => parameterReplies.has("subscribed"));
  out({ event: "parametersSubscribed" });
}
await until(() => pushed(plan.awaitBefore));
if (plan.getParameters) {
  client.getParameters(plan.getParameters, "get");
  await until(() => parameterReplies.has("get"));
  out({ event: "parameters", id: "get", parameters: parameterReplies.get("get") });
}
let k = 0;
for (const params of plan.setParameters ?? []) {
  const id = `set${k++}`;
  const before = statuses.length;
  client.setParameters(params, id);
  await until(() => parameterReplies.has(id));
  await sleep(500); // a refusal's status follows the reply
  out({ event: "parameters", id, parameters: parameterReplies.get(id), statuses: statuses.slice(before) });
}
await until(() => pushed(plan.awaitAfter));
if (plan.watchMs !== undefined) {
  await sleep(plan.watchMs); // anything pushed twice arrives within this
  out({ event: "pushes", pushes });
}
let callId = 1;
for (const name of plan.services ?? []) {
  const service = services.get(name);
  const id = callId++;
  // std_srvs/Trigger_Request is empty: CDR header + the one byte rmw writes for an empty struct
  client.sendServiceCallRequest({ serviceId: service.id, callId: id, encoding: "cdr",
                                  data: new Uint8Array([0, 1, 0, 0, 0]) });
  await until(() => serviceReplies.has(id));
  const reply = serviceReplies.get(id);
  if (reply.ok) {
    const schema = service.response?.schema ?? service.responseSchema;
    const reader = new MessageReader(parse(schema, { ros2: true }));
    const d = reply.m.data;
    out({ event: "service", name, ok: true, encoding: reply.m.encoding,
          value: reader.readMessage(new Uint8Array(d.buffer, d.byteOffset, d.byteLength)) });
  } else {
    out({ event: "service", name, ok: false, message: reply.message });
  }
}
out({ event: "done", received: Object.fromEntries(received) });
client.close();
await new Promise(() => finish(0));
