// An independent OPC UA client (node-opcua, not asyncua) for tests/test_opcua.py.
//
//   node opcua.js run ENDPOINT CELL USER PASSWORD PLAN TIMEOUT_S
//     browse Objects/Machines/CELL, read its identification and plans, subscribe to the job's
//     progress, call StartJob(PLAN) and follow the job to its end.
//   node opcua.js refused ENDPOINT CELL USER PASSWORD PLAN
//     call StartJob(PLAN) and StartJob() without its argument; report the status codes and
//     LastError.
//   node opcua.js results ENDPOINT CELL USER PASSWORD
//     read every variable of Results.
//
// Prints one JSON object on stdout.
"use strict";
const {
  OPCUAClient, AttributeIds, ClientSubscription, ClientMonitoredItem, TimestampsToReturn,
  DataType, UserTokenType, MessageSecurityMode, SecurityPolicy,
} = require("node-opcua-client");

async function main() {
  const [mode, endpoint, cell, user, password, plan, timeoutS] = process.argv.slice(2);
  const client = OPCUAClient.create({
    endpointMustExist: false, securityMode: MessageSecurityMode.None,
    securityPolicy: SecurityPolicy.None, connectionStrategy: { maxRetry: 2, initialDelay: 200 },
  });
  await client.connect(endpoint);
  const session = await client.createSession(
    { type: UserTokenType.UserName, userName: user, password: password });
  const out = {};
  try {
    // browse from the root: Objects -> Machines -> <cell>
    const paths = await session.translateBrowsePath([
      `/Objects/2:Machines/2:${cell}`, `/Objects/2:Machines/2:${cell}/2:Job/2:ProgressPercent`,
      `/Objects/2:Machines/2:${cell}/2:Job/2:State`, `/Objects/2:Machines/2:${cell}/2:Job/2:Station`,
      `/Objects/2:Machines/2:${cell}/2:Plans`, `/Objects/2:Machines/2:${cell}/2:LastError`,
      `/Objects/2:Machines/2:${cell}/2:Identification/2:Manufacturer`,
      `/Objects/2:Machines/2:${cell}/2:StartJob`,
    ].map((p) => require("node-opcua-client").makeBrowsePath("RootFolder", p)));
    const ids = paths.map((r) => (r.targets && r.targets.length ? r.targets[0].targetId : null));
    const [cellId, progressId, stateId, stationId, plansId, errorId, manufId, startId] = ids;
    out.resolved = ids.map((i) => i !== null);
    const browsed = await session.browse(cellId);
    out.children = browsed.references.map((r) => r.browseName.name).sort();
    out.manufacturer = (await session.read({ nodeId: manufId, attributeId: AttributeIds.Value }))
      .value.value;
    out.plans = (await session.read({ nodeId: plansId, attributeId: AttributeIds.Value }))
      .value.value;
    const call = (args) => session.call({ objectId: cellId, methodId: startId,
                                          inputArguments: args });
    if (mode === "results") {
      const names = ["LastJobId", "Stations", "OverlapMeanMm", "StationsSkipped",
                     "StationsMissing", "LastResultPass"];
      const found = await session.translateBrowsePath(names.map((n) =>
        require("node-opcua-client").makeBrowsePath(
          "RootFolder", `/Objects/2:Machines/2:${cell}/2:Results/2:${n}`)));
      for (let i = 0; i < names.length; i += 1) {
        const v = (await session.read({ nodeId: found[i].targets[0].targetId,
                                        attributeId: AttributeIds.Value })).value;
        out[names[i]] = Array.isArray(v.value) || ArrayBuffer.isView(v.value)
          ? Array.from(v.value) : v.value;
      }
      return out;
    }
    if (mode === "refused") {
      const r1 = await call([{ dataType: DataType.String, value: plan }]);
      out.start = r1.statusCode.name;
      out.error_after_start = (await session.read({ nodeId: errorId,
                                                    attributeId: AttributeIds.Value })).value.value;
      const r2 = await call([]);
      out.no_args = r2.statusCode.name;
      const r3 = await call([{ dataType: DataType.Double, value: 3.5 }]);
      out.wrong_type = r3.statusCode.name;
      out.error_after_wrong = (await session.read({ nodeId: errorId,
                                                    attributeId: AttributeIds.Value })).value.value;
      return out;
    }
    const sub = ClientSubscription.create(session, {
      requestedPublishingInterval: 100, requestedMaxKeepAliveCount: 20,
      requestedLifetimeCount: 600, maxNotificationsPerPublish: 100, publishingEnabled: true,
      priority: 10 });
    out.progress = []; out.states = []; out.stations = [];
    const watch = (nodeId, list) => {
      const item = ClientMonitoredItem.create(sub, { nodeId, attributeId: AttributeIds.Value },
        { samplingInterval: 50, discardOldest: false, queueSize: 100 },
        TimestampsToReturn.Both);
      item.on("changed", (dv) => list.push(dv.value.value));
    };
    watch(progressId, out.progress); watch(stateId, out.states); watch(stationId, out.stations);
    await new Promise((r) => setTimeout(r, 500));
    const r = await call([{ dataType: DataType.String, value: plan }]);
    out.start = r.statusCode.name;
    out.job_id = r.outputArguments.length ? r.outputArguments[0].value : null;
    const deadline = Date.now() + 1000 * Number(timeoutS || 120);
    while (Date.now() < deadline) {
      const last = out.states[out.states.length - 1];
      if (out.states.includes("running") && ["done", "failed", "aborted"].includes(last)) break;
      await new Promise((res) => setTimeout(res, 200));
    }
    await new Promise((res) => setTimeout(res, 500));
    await sub.terminate();
    return out;
  } finally {
    await session.close();
    await client.disconnect();
  }
}

main().then((out) => { console.log(JSON.stringify(out)); process.exit(0); })
  .catch((err) => { console.error(String(err && err.stack || err)); process.exit(1); });
